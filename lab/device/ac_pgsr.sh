# Lease step ac (#59): the TopoSurfel authors' code at its published counts (30,000 warm-up + 10,000 mesh-stage
# iterations) in two leases, since the whole does not fit one lease's device time. The mesh stage reads nothing of
# the warm-up but its TSDF mesh, so the warm-up's result folder travels from the first lease to the second
# (run_pgsr.py --from-warmup), and the row counts both leases' time and the larger peak.
#   lease 1, after the p1 and p2 staging calls, carrying .stage/p3 .stage/gl .stage/small (+ .stage/dtu_raw for DTU):
#     SCENE=bunny64 [BESIDE="chair torus_sparse"] bash lab/device/ac_pgsr.sh warmup   # launches, waits, scores
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh wait        # again within 30 s until scored
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh pack        # until "all parts sent"
#   then copy the returned $OUT/ac/warm_SCENE.part* to .stage/warm/ here.
#   lease 2, after p1 and p2, carrying .stage/p3 .stage/gl .stage/small .stage/warm (+ .stage/dtu_raw):
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh meshstage   # unpacks the warm-up, launches pgsr from it, waits
#     SCENE=bunny64 bash lab/device/ac_pgsr.sh wait        # until scored into $OUT/ac/rows_SCENE.json
source lab/device/lease_env.sh
t0=$(date +%s)
SCENE=${SCENE:-bunny64}
step=${1:-wait}
setup() {  # $1: the peer folders to stage
  mkdir -p $S/whl $S/gl $S/peers
  cp .stage/p3/* $S/ && cp .stage/small/whl/* $S/whl/ && cp .stage/gl/* $S/gl/
  for p in $1; do cp -r .stage/small/peers/$p $S/peers/; done
  lease_install || exit 1
  # bunny64 is the built-in bunny at 64 views of 512 px (peers.md's run); the benchmark's scenes export by name
  [ $SCENE = bunny64 ] && [ ! -f $S/exch/bunny64/meta.json ] && python3 benchmarks/peers/export.py bunny \
    $S/exch/bunny64 --views 64 --resolution 512 --name bunny64 > $S/exch_bunny64.log 2>&1 &
  lease_prepare $( [ $SCENE = bunny64 ] || echo $SCENE) ${BESIDE:-}
  wait
  echo "staged and built after $(( $(date +%s) - t0 )) s"
}
case $step in
warmup)
  # BESIDE="chair torus_sparse": 2DGS at its 30,000 iterations on those scenes beside the warm-up (they end first)
  setup "pgsr_dpsr pgsr_init ${BESIDE:+2dgs}"
  STAGE=$S bash $D launch "$S/exch/$SCENE" -- pgsr_nomesh
  for sc in ${BESIDE:-}; do STAGE=$S bash $D launch "$S/exch/$sc" -- 2dgs; done
  SYS="pgsr_nomesh${BESIDE:+ 2dgs}" ;;
meshstage)
  mkdir -p $S/warm/$SCENE
  cat .stage/warm/warm_$SCENE.part* | xz -d | tar -x -C $S/warm/$SCENE || exit 1
  ls -la $S/warm/$SCENE $S/warm/$SCENE/warmup/mesh
  setup "pgsr_dpsr pgsr_init nvdiffrast diso"
  PGSR_ARGS="--from-warmup $S/warm/$SCENE" STAGE=$S bash $D launch "$S/exch/$SCENE" -- pgsr
  SYS=pgsr ;;
wait) SYS=$(cat $S/ac_system) ;;
pack)
  # the warm-up's result for the second lease (its run.json and TSDF mesh), xz in parts of 15 MiB, four a call (a
  # call brings back 64 MiB): call it until it says "all parts sent"
  r=$S/res/$SCENE/pgsr_nomesh
  mkdir -p $S/pack $OUT/ac
  ls $S/pack/warm_$SCENE.part* >/dev/null 2>&1 || \
    tar -C $r -c run.json warmup/mesh/tsdf_fusion_post.ply | xz -T0 -6 | split -b 15M - $S/pack/warm_$SCENE.part
  n=0
  for f in $S/pack/warm_$SCENE.part*; do
    [ -f $f.sent ] && continue
    [ $n = 4 ] && break
    cp $f $OUT/ac/ && touch $f.sent && n=$((n + 1))
  done
  ls -la $S/pack
  ls $S/pack/warm_$SCENE.part?? | while read f; do [ -f $f.sent ] || echo "left: $f"; done | grep -q left \
    && echo "parts left: call pack again" || echo "all parts sent"
  exit 0 ;;
*) echo "unknown step $step"; exit 2 ;;
esac
echo $SYS > $S/ac_system
TAG=ac SYSTEMS=$SYS WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/w_wait.sh
[ "${SYS%% *}" = pgsr_nomesh ] && [ -f $S/scored/$SCENE ] && echo "scored: now SCENE=$SCENE bash lab/device/ac_pgsr.sh pack"
