# Lease step b (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and .stage/dtu_raw):
# gsplat's JIT build, then on the quiet GPU lab/raster_forward.py (#60 goal 2, the public forward alone against
# gsplat's at 100k and 1M surfels with tile sizes 8 / 16 and prefetch batches 16 / 32, with kernel tables), then
# test_fit_graphs.py on the CPU beside d40.sh's DTU fits (VARIANTS and SEEDS as d40.sh takes them).
source lab/device/lease_env.sh
t0=$(date +%s)
R=$PWD
lease_dtu || exit 1
MAX_JOBS=14 STAGE=$S timeout 300 bash $D build 2>&1 | grep -i gsplat | tail -n 2
echo "gsplat built after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout 200 python3 $R/lab/raster_forward.py --profile 2>&1 | grep -v Warning | tail -n 70)
echo "forward done after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout 250 python3 -m pytest -q -p no:cacheprovider $R/tests/test_fit_graphs.py 2>&1 | tail -n 3 \
  > /tmp/b_tests.txt) &
bash lab/device/d40.sh 2>&1 | tail -n 12
wait
echo "--- test_fit_graphs.py on the CPU"; cat /tmp/b_tests.txt
echo "done after $(( $(date +%s) - t0 )) s"
