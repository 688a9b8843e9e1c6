# Lease step x (#59, the polish's figure on the GPU): the 64-view chair and bunny64 at the CUDA default (1,000
# polish iterations after the 2,000 of the co-evolution), without the polish, and with 2,000; the chair's gap to
# gsplat was 0.48 dB with the loop costing 0.23 (benchmarks/peers.md). After the p1, p2 and p3 + gl + small/whl
# staging calls, in one call: `bash lab/device/x_polish.sh`; then `TAG=x bash lab/device/wait_fits.sh` calls
# (within 30 s of each other) until it has scored both scenes into $OUT/x/rows_SCENE.json.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
[ -f $S/exch/bunny64/meta.json ] || python3 benchmarks/peers/export.py bunny $S/exch/bunny64 --views 64 \
  --resolution 512 --name bunny64 > $S/exch_bunny64.log 2>&1 &
lease_prepare chair
wait
run() {  # SCENE NAME ARGS...
  local sc=$1 d=$S/res/$1/wtopo_$2; shift 2; mkdir -p $d
  setsid nohup timeout 900 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label $(basename $d) "$@" \
    > $d.log 2>&1 < /dev/null &
}
for sc in chair bunny64; do
  run $sc x_polish1000
  run $sc x_polish0 --set polish.iterations=0
  run $sc x_polish2000 --set polish.iterations=2000
done
echo "fits launched after $(( $(date +%s) - t0 )) s"
TAG=x WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
