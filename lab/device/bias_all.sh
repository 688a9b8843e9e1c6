# Lease step "bias" (#59: wtopo's meshes lie inside the surface, benchmarks/peers.md's bunny64 note): the CUDA
# default beside the same fit with about twice the re-initialisation's surfels, on bunny64 (where the authors' warm-up
# is closer) and the dense bowl, mug and torus. The re-initialisation keeps one surfel per face of a TSDF mesh from
# a grid of at most 128 voxels (the CPU bunny's: 72,097 faces), under the plan's CUDA cap of 100,000 (its footprint
# rule asks 132,000 on bunny64): the variant fuses on 192 voxels and keeps up to FACES (200,000). At the CPU default
# three times its cap moved the bunny's surfels closer to the surface but made the hard suite worse
# (design/decisions.md, "Open: wtopo's meshes lie inside the surface"); a CUDA fit has 7.5x the iterations. The
# signed step prints each fit's reinit_faces and reinit_surfels: what the variant changed. A third chain narrows the
# render's low-pass from the CUDA plan's 0.25 px to FILTER (0.15): its halo around edge-on surfels is what the mask
# and photometric terms pull the silhouette in against (design/decisions.md), and at the CPU default 0.15 px brought
# the bunny's depth offset from 0.28 to 0.20 % of the diagonal (medians) and its Chamfer from 0.200 to 0.181 %. After
# the staging calls of
# lab/device/alone.sh (p1, p2, p3, then install), in one call:   bash lab/device/bias_all.sh
# then `TAG=b_ WAIT=180 bash lab/device/wait_fits.sh` calls (within 30 s of each other; the call that finds every fit
# done scores the four scenes, up to 100 s each, inside the call's 600 s) until it has scored every scene into
# $OUT/b_/rows_SCENE.json; then `bash lab/device/bias_all.sh signed` prints each mesh's signed offset
# (lab/signed_error.py). Three fits at a time (the chains side by side): the times compare within a lease, not
# with fits alone.
source lab/device/lease_env.sh
t0=$(date +%s)
SCENES=${SCENES:-bunny64 bowl mug torus}
FACES=${FACES:-200000}
if [ "${1:-}" = signed ]; then
  for sc in $SCENES; do python3 lab/signed_error.py $S/exch/$sc/gt.ply $S/res/$sc/wtopo_b_*/mesh.ply 2>&1 | tail -n 2
    for d in $S/res/$sc/wtopo_b_*/; do  # what the variant changed: the re-initialisation's surfels
      grep -ho '"reinit_[a-z_]*": *[0-9]*' $(find $d -name report.json) 2>/dev/null | tr '\n' ' '; echo " $d"
    done
  done
  exit 0
fi
python3 -c "import warp, wtopo" 2>/dev/null || { lease_install || exit 1; }
for sc in $SCENES; do  # the scenes, exported here (lease_prepare would also build the staged peers)
  [ -f $S/exch/$sc/meta.json ] && continue
  args=($sc); [ $sc = bunny64 ] && args=(bunny --views 64 --resolution 512)
  python3 benchmarks/peers/export.py "${args[@]}" $S/exch/$sc --name $sc > $S/exch_$sc.log 2>&1 &
done
wait
for sc in $SCENES; do [ -f $S/exch/$sc/meta.json ] || { echo "$sc: export failed"; tail -n 3 $S/exch_$sc.log; exit 1; }; done
chain() {  # NAME ARGS...: every scene's fit, one after another, in one detached chain
  local name=$1 job="" sc d
  shift
  for sc in $SCENES; do
    d=$S/res/$sc/wtopo_$name; mkdir -p $d
    job="${job:+$job; }timeout 900 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label wtopo_$name $* > $d.log 2>&1; echo \$? > $d.rc"
  done
  setsid nohup bash -c "$job" > /dev/null 2>&1 < /dev/null &
}
chain b_default
chain b_faces --set tsdf.resolution=192 --set tsdf.max_faces=$FACES
chain b_filter --set filter_sigma=${FILTER:-0.15}
echo "three chains of $(echo $SCENES | wc -w) fits launched after $(( $(date +%s) - t0 )) s"
TAG=b_ WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
