# Lease step l in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw and .stage/mvs_old.py):
# #59's 64-view chair, where gsplat read 2.8 dB sharper (2.1 of it the harness's render filter, since fixed): gsplat at its 30,000 iterations
# and wtopo at the default (and two variants) side by side (gsplat's run takes about 760 s: lab/device/l_wait.sh waits for it),
# then score.py --render-pictures puts each held-out view's photo beside both renders and their errors; on the side,
# bench_mvs.py times the stereo against its module at 3fe093d (the working tree on the device may have no .git:
# stage that file as .stage/mvs_old.py first).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare chair bunny64 dtu_scan24
STAGE=$S bash $D launch "$S/exch/chair" -- gsplat
# wtopo at the default and two hypotheses for the gap, side by side: four times the re-initialisation's surfels
# (one per face: 64k at the default) and SH degree 3 (the plan gives the diffuse chair 0; gsplat fits 3), and
# the surfels on bunny64 (the default reaches the CUDA cap of 100k faces there); DTU at the default, all
# rendered with the fit's own filter since 7377451 (run_wtopo.py)
for v in "chair l" "chair l_faces --set tsdf.max_faces=250000" "chair l_sh3 --set sh_degree=3" "bunny64 l" \
         "bunny64 l_faces --set tsdf.max_faces=250000" "dtu_scan24 l"; do
  set -- $v; sc=$1; d=$S/res/$sc/wtopo_$2; shift 2; mkdir -p $d
  # detached: the fits outlive this call (l_wait.sh waits for their run.json)
  setsid nohup timeout 1200 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label $(basename $d) "$@" \
    > $d.log 2>&1 < /dev/null &
done
# the stereo against its previous module in one process (beside gsplat's training: read the ratio)
mkdir -p $OUT/l; git show 3fe093d:wtopo/geometry/mvs.py > /tmp/mvs_old.py 2>/dev/null || cp .stage/mvs_old.py /tmp/mvs_old.py
timeout 150 python3 benchmarks/bench_mvs.py --device cuda --views 42 --data .stage/dtu_raw/dtu_scan24 --against /tmp/mvs_old.py > $OUT/l/mvs_gpu.txt 2>&1
tail -n 4 $OUT/l/mvs_gpu.txt
WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/l_wait.sh
