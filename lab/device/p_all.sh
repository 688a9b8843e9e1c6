# Lease step p in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw and .stage/old, a `git archive` of the tree before the change): #60's host time per iteration.
# The bridge's views and the hot ops' allocations through torch (this tree) against the tree before (.stage/old),
# DTU at the CUDA default, profiled, alone on the GPU, one after the other; the new tree runs first and also
# compiles the kernels, so the old tree's run finds a warm cache (the comparison favours the old tree).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir --target $S/old_site .stage/old \
  > $S/old_install.log 2>&1 || { tail -5 $S/old_install.log; exit 1; }
python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 $S/exch/dtu_scan24 --name dtu_scan24 > $S/exch_dtu.log 2>&1
tail -n 1 $S/exch_dtu.log
echo "installed and exported after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/p
run() {  # NAME [PYTHONPATH prefix]
  local d=$S/res/dtu_scan24/$1; mkdir -p $d
  PYTHONPATH=${2:+$2:}$PYTHONPATH timeout 280 python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $d \
    --label $1 --set runtime.profile=true > $d.log 2>&1
  echo "$1 rc=$? after $(( $(date +%s) - t0 )) s"; tail -n 3 $d.log
  cp $d/run/report.json $OUT/p/report_$1.json 2>/dev/null
  python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(r.get('psnr'), r.get('iterations'), r.get('elapsed_s')); from wtopo.fitting.profiling import format_profile; print(format_profile(r.get('profile')))" $d/run/report.json | head -n 45
}
# RUNS="new" runs this tree alone (the old tree's row then comes from an earlier call)
for r in ${RUNS:-new old new2}; do
  [ $(( $(date +%s) - t0 )) -lt 380 ] || break
  case $r in old) run old $S/old_site ;; *) run $r ;; esac
done
echo "call ends after $(( $(date +%s) - t0 )) s"
