# Lease step ac (#59): the TopoSurfel authors' code at its published counts (30,000 warm-up + 10,000 mesh-stage
# iterations) in two leases, since the whole does not fit one lease's device time. The mesh stage reads nothing of
# the warm-up but its TSDF mesh, so the warm-up's result folder travels from the first lease to the second
# (run_pgsr.py --from-warmup), and the row counts both leases' time and the larger peak (with BESIDE, the warm-up's
# time is of a GPU shared with 2DGS's runs: an upper bound, as every time in peers.md).
# Both leases should read one exchange folder (the warm-up names its exchange and the mesh stage checks it): after the
# p1 and p2 staging calls, a call carrying .stage/exch runs `mkdir -p /root/peers/exch && cp -r .stage/exch/bunny64
# /root/peers/exch/` (the bunny64 the other systems' rows read; without it setup exports one on the machine).
#   lease 1, then carrying .stage/p3 .stage/gl .stage/small (+ .stage/dtu_raw for DTU):
#     SCENE=bunny64 [BESIDE="chair torus_sparse"] bash lab/device/ac_pgsr.sh warmup   # launches, waits, scores
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh wait        # again within 30 s until scored
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh pack        # until "all parts sent"
#   then put the returned $OUT/ac/warm_SCENE.part?? here in folders of at most four, .stage/warm/1, .stage/warm/2, ...
#   lease 2, after p1, p2 and the exchange's call, one call per folder, each carrying that folder alone:
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh carry
#   then, carrying .stage/p3 .stage/gl .stage/small (+ .stage/dtu_raw):
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh meshstage   # unpacks the warm-up, launches pgsr from it, waits
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh wait        # until scored into $OUT/ac/rows_SCENE.json
source lab/device/lease_env.sh
t0=$(date +%s)
SCENE=${SCENE:-bunny64}
step=${1:-wait}
setup() {  # $1: the peer folders to stage, $2: the modules their builds must make importable
  mkdir -p $S/whl $S/gl $S/peers
  # every staged wheel but gsplat's: nothing here runs gsplat, and its JIT build would take the cores the peers'
  # CUDA builds need
  cp .stage/p3/* $S/ && cp .stage/gl/* $S/gl/ && ls .stage/small/whl/*.whl | grep -v /gsplat- | xargs -I{} cp {} $S/whl/
  for p in $1; do cp -r .stage/small/peers/$p $S/peers/; done
  lease_install || exit 1
  lease_prepare $SCENE ${BESIDE:-}
  for m in $2; do python3 -c "import $m" 2>&1 | tail -n 1 | sed "s/^/import $m: /"; done  # a failed build shows here
  echo "staged and built after $(( $(date +%s) - t0 )) s"
}
case $step in
warmup)
  # BESIDE="chair torus_sparse": 2DGS at its 30,000 iterations on those scenes beside the warm-up (they end first)
  setup "pgsr_dpsr pgsr_init ${BESIDE:+2dgs}" "diff_plane_rasterization simple_knn._C ${BESIDE:+diff_surfel_rasterization}"
  STAGE=$S bash $D launch "$S/exch/$SCENE" -- pgsr_nomesh
  for sc in ${BESIDE:-}; do STAGE=$S bash $D launch "$S/exch/$sc" -- 2dgs; done
  SYS="pgsr_nomesh${BESIDE:+ 2dgs}" ;;
meshstage)
  set -o pipefail
  mkdir -p $S/warm/$SCENE
  cat $S/warmparts/warm_$SCENE.part?? | xz -d | tar -x -C $S/warm/$SCENE || exit 1
  ls -la $S/warm/$SCENE $S/warm/$SCENE/warmup/mesh
  setup "pgsr_dpsr pgsr_init nvdiffrast diso" "diff_plane_rasterization simple_knn._C nvdiffrast.torch diso"
  PGSR_ARGS="--from-warmup $S/warm/$SCENE" STAGE=$S bash $D launch "$S/exch/$SCENE" -- pgsr
  SYS=pgsr ;;
wait) SYS=$(cat $S/ac_system) ;;
pack)
  # the warm-up's result for the second lease (its run.json and TSDF mesh), xz in parts of 10 MiB, six a call (a
  # call brings back 8 files, 64 MiB): call it until it says "all parts sent"; RESEND=1 sends every part again
  set -o pipefail
  r=$S/res/$SCENE/pgsr_nomesh
  for f in $S/scored/$SCENE $r/run.json $r/warmup/mesh/tsdf_fusion_post.ply; do
    [ -f $f ] || { echo "pack: no $f (not scored yet?)"; exit 1; }
  done
  mkdir -p $S/pack/sent $OUT/ac
  [ -n "${RESEND:-}" ] && rm -f $S/pack/sent/*
  if [ ! -f $S/pack/done_$SCENE ]; then
    rm -f $S/pack/warm_$SCENE.part* $S/pack/tmp_$SCENE.*
    tar -C $r -c run.json warmup/mesh/tsdf_fusion_post.ply | xz -T0 -6 | split -b 10M - $S/pack/tmp_$SCENE. \
      || { echo "pack: tar | xz | split failed"; exit 1; }
    for f in $S/pack/tmp_$SCENE.??; do mv $f $S/pack/warm_$SCENE.part${f##*.}; done
    touch $S/pack/done_$SCENE
  fi
  n=0 left=0
  for f in $S/pack/warm_$SCENE.part??; do
    [ -f $S/pack/sent/${f##*/} ] && continue
    if [ $n -lt 6 ]; then cp $f $OUT/ac/ && touch $S/pack/sent/${f##*/} && n=$((n + 1)); else left=$((left + 1)); fi
  done
  ls -la $S/pack $OUT/ac
  [ $left = 0 ] && echo "all parts sent" || echo "$left parts left: call pack again"
  exit 0 ;;
carry)
  # lease 2's staging of the warm-up: each call carries one folder .stage/warm/N (at most 40 MiB beside the tree)
  mkdir -p $S/warmparts && cp .stage/warm/*/warm_$SCENE.part?? $S/warmparts/ && ls -la $S/warmparts
  exit 0 ;;
*) echo "unknown step $step"; exit 2 ;;
esac
echo $SYS > $S/ac_system
TAG=ac SYSTEMS=$SYS WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/w_wait.sh
[ "${SYS%% *}" = pgsr_nomesh ] && [ -f $S/scored/$SCENE ] && echo "scored: now SCENE=$SCENE bash lab/device/ac_pgsr.sh pack"
