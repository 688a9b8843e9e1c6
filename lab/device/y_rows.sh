# Lease step y (#59's wtopo rows at today's default; after the p1, p2 and p3 + gl + small/whl staging calls and a
# lease step that installed, e.g. z_all.sh): exports each of SCENES (default: chair_sparse, the ten-view chair, which
# gains the polish), runs wtopo's CUDA default on each, detached and side by side, then waits up to WAIT seconds and
# scores them into $OUT/y/rows_SCENE.json (call TAG=y bash lab/device/wait_fits.sh again if they are still running).
source lab/device/lease_env.sh
lease_dtu || exit 1
for sc in ${SCENES:-chair_sparse}; do
  [ -f $S/exch/$sc/meta.json ] || python3 benchmarks/peers/export.py $sc $S/exch/$sc --name $sc > $S/exch_$sc.log 2>&1
  mkdir -p $S/res/$sc
  d=$S/res/$sc/wtopo_y
  setsid nohup timeout 900 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label wtopo > $d.log 2>&1 < /dev/null &
done
TAG=y WAIT=${WAIT:-420} bash lab/device/wait_fits.sh
