# Lease step "bias" (#59: wtopo's meshes lie inside the surface, benchmarks/peers.md's bunny64 note, design/decisions.md
# "Open: wtopo's meshes lie inside the surface"): chains of fits side by side, each over SCENES (bunny64, where the
# authors' warm-up is closer, and the dense bowl, chair and mug), one per name in CHAINS:
#   default   the CUDA default (since 418e1f9 with the photometric term blind to the ring outside the mask, since
#             a1ff951 with the outline offset), and beside it, as wtopo_b_default_pre, the same fit's mesh before the
#             outline offset (lab/pre_outline.py: the offset's gain without the run-to-run spread);
#   plain     the CUDA default alone (no second folder: the unbounded scenes and DTU have no outline offset);
#   seedN     the same at seed N (seed1, seed2, ...);
#   filter    the render's low-pass narrowed from the CUDA plan's 0.25 px to FILTER (0.15): at the CPU default 0.15 px
#             brought the bunny's depth offset from 0.28 to 0.20 % of the diagonal and its Chamfer from 0.200 to
#             0.181 %, but the chair, chair_box and the bowl 4-10 % farther;
#   maskwarm  the mask term through the warm-up only (lab/mask_warmup_only.py; PGSR has none): on the CPU bunny the
#             mesh moved from 0.057 to 0.036 % inside, Chamfer 0.2015 against 0.200 %, F 0.946 against 0.954;
#   trunc     the final fusion truncated at TRUNC (2) voxels, not 4 (lab/final_truncation.py): fused from the true
#             depths, 4 voxels thicken the thin chair (at the CPU default the torus +38 %, the mug +58 %);
#   ring      the photometric and mask terms blind to a RING (1) px ring outside the mask (lab/ring_blind.py): on the
#             CPU suite the blob 0.234 -> 0.105 %, the torus 0.143 -> 0.075 %, the chairs +37-38 %;
#   ringphoto the photometric term alone blind to that ring (the mask term sees it);
#   ringsoft  the photometric term blind to the ring, the mask term's target there SOFT (0.5), not 0;
#   decay     the fusion's weights behind a view's depth fading out from DECAY (2) voxels (lab/fusion_decay.py);
#   thindecay that fading in the final fusion only, of fits whose co-evolution found thin parts;
#   ringdecay ring, and the fusion's weights behind a view's depth fading out from DECAY (2) voxels
#             (lab/fusion_decay.py): the true depths fused no longer thicken the thin chair;
#   proxy     the proxy's Poisson grid at PROXY (320) nodes, not the plan's 128-256 (bunny64: 208, a cell of two pixel
#             footprints; design/decisions.md "Where bunny64's gap to PGSR is now": the coarse proxy rounds the
#             concave and sharp places where wtopo's mesh is farther than PGSR's);
#   sigma     the Poisson solve's smoothing at SIGMA (0.5) cells, not 1 (both chains also move which fits find thin
#             parts, whose rule measures on the proxy's grid and its smoothing: on the CPU a fixed 128 grid left the
#             chair's unfound, +36 %; compare each report's "coevolution" entry);
#   nooutline the final mesh left where the fusion put it (final.outline=false; the default since the outline offset
#             moves a masked object's mesh until its silhouettes cover the training masks, wtopo/geometry/outline.py);
#   faces     about twice the re-initialisation's surfels (a TSDF of 192 voxels, up to FACES = 200,000 faces; the
#             CPU bunny's 128-voxel mesh has 72,097, under the CUDA cap of 100,000).
#   fusion    the default, and beside it a result folder per final-fusion variant of the same depths (FUSION, K:T:F,...:
#             the voxel times K, truncation T voxels, face tolerance F voxels; lab/scene_fusion.py): for dtu_scan24
#             (exported from .stage/dtu_raw, lease_env.sh's lease_dtu) and the unbounded scenes (design/decisions.md
#             "Not changed: the scene fusion's grid and the face rule's tolerance"); score.py --pictures draws them.
#   geo       PGSR's multi-view geometric consistency at weight GEO (0.03; lab/geo_consistency.py): a second render
#             per step, eager (the graphs replay the first only).
# After the staging calls of lab/device/alone.sh (p1, p2, p3, then install), in one call:   bash lab/device/bias_all.sh
# then `TAG=b_ WAIT=180 bash lab/device/wait_fits.sh` calls (within 30 s of each other; the call that finds every fit
# done scores the scenes, up to 100 s each, inside the call's 600 s) until it has scored every scene into
# $OUT/b_/rows_SCENE.json; then `bash lab/device/bias_all.sh signed` prints each mesh's signed offset
# (lab/signed_error.py, every mesh's) and re-initialisation counts. The chains share the GPU: their times compare
# within a lease, not with fits alone. rows_2026-12-07a: SCENES="bunny64 chair", then SCENES=bowl. rows_2026-12-07c
# (eight fits at once, after alone.sh install in the same call): the exports first, SCENES="bunny64 chair bowl mug"
# CHAINS=" " NOWAIT=1, then for each scene SCENES=$sc CHAINS="default filter" NOWAIT=1, then
# TAG=b_ WAIT=... PAR=1 bash lab/device/wait_fits.sh and this script's signed step.
source lab/device/lease_env.sh
t0=$(date +%s)
SCENES=${SCENES:-bunny64 bowl chair mug}
CHAINS=${CHAINS:-default filter maskwarm}
FACES=${FACES:-200000}
if [ "${1:-}" = signed ]; then
  for sc in $SCENES; do python3 lab/signed_error.py $S/exch/$sc/gt.ply $S/res/$sc/wtopo_b_*/mesh.ply 2>&1 | grep mesh.ply
    for d in $S/res/$sc/wtopo_b_*/; do  # what the variant changed: the re-initialisation's surfels
      grep -ho '"reinit_[a-z_]*": *[0-9]*' $(find $d -name report.json) /dev/null 2>/dev/null | tr '\n' ' '; echo " $d"
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
chain() {  # NAME ENV ARGS...: every scene's fit, one after another, in one detached chain (ENV: - or VAR=1)
  local name=$1 env=$2 job="" sc d
  shift 2
  [ -n "${NOUSD:-}" ] && set -- "$@" --set runtime.usd_every=0  # NOUSD=1: no timeline (usd-core not staged)
  [ "$env" = - ] && env=""
  for sc in $SCENES; do  # $d.rc when the fit ends, and ${d}_pre.rc for lab/pre_outline.py's folder (KEEP_PRE_OUTLINE)
    d=$S/res/$sc/wtopo_$name; mkdir -p $d
    job="${job:+$job; }$env timeout 900 python3 lab/device/patched_run.py $S/exch/$sc $d --label wtopo_$name $* > $d.log 2>&1; echo \$? | tee $d.rc > ${d}_pre.rc"
  done
  setsid nohup bash -c "$job" > /dev/null 2>&1 < /dev/null &
}
for c in $CHAINS; do
  case $c in
    default) chain b_default KEEP_PRE_OUTLINE=1 ;;
    plain) chain b_plain - ;;
    seed[0-9]*) chain b_$c KEEP_PRE_OUTLINE=1 --set runtime.seed=${c#seed} ;;
    nooutline) chain b_nooutline - --set final.outline=false ;;
    faces) chain b_faces - --set tsdf.resolution=192 --set tsdf.max_faces=$FACES ;;
    proxy) chain b_proxy - --set mesh.resolution=${PROXY:-320} ;;
    sigma) chain b_sigma - --set mesh.sigma=${SIGMA:-0.5} ;;
    filter) chain b_filter - --set filter_sigma=${FILTER:-0.15} ;;
    maskwarm) chain b_maskwarm MASK_WARMUP_ONLY=1 ;;
    trunc) chain b_trunc FINAL_TRUNCATION=${TRUNC:-2} ;;
    ring) chain b_ring RING_BLIND=${RING:-1} ;;
    ringphoto) chain b_ringphoto "RING_BLIND=${RING:-1} RING_TERMS=photo" ;;
    ringsoft) chain b_ringsoft "RING_BLIND=${RING:-1} RING_MASK_TARGET=${SOFT:-0.5}" ;;
    decay) chain b_decay FUSION_DECAY=${DECAY:-2} ;;
    thindecay) chain b_thindecay "FUSION_DECAY=${DECAY:-2} DECAY_THIN_ONLY=1" ;;
    ringdecay) chain b_ringdecay "RING_BLIND=${RING:-1} FUSION_DECAY=${DECAY:-2}" ;;
    fusion) chain b_fusion SCENE_FUSION=${FUSION:-1:4:5,1:4:1e6,0.5:4:2,2:4:2} ;;
    geo) chain b_geo GEO_CONSISTENCY=${GEO:-0.03} ;;
    *) echo "unknown chain $c"; exit 1 ;;
  esac
done
echo "chains $CHAINS of $(echo $SCENES | wc -w) fits launched after $(( $(date +%s) - t0 )) s"
[ -n "${NOWAIT:-}" ] && exit 0  # NOWAIT=1: launch only (several calls of this script in one command), then wait_fits.sh
TAG=b_ WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
