# Lease step u in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): the graphed per-pixel loss terms on the H200, their CUDA tests, then DTU at the CUDA default to
# its end with lab/device/t_loop.py's windows (--full: wall per iteration, kernels, host profile; PSNR, time).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_dtu || exit 1
mkdir -p $OUT/u
echo "installed and exported after $(( $(date +%s) - t0 )) s"
R=$PWD
(cd /tmp && timeout 150 python3 -m pytest -q -p no:cacheprovider $R/tests/test_pixel_terms.py $R/tests/test_bridge.py \
  $R/tests/test_cuda_equality.py 2>&1 | tail -n 6)
echo "tests after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout ${U_TIMEOUT:-250} python3 $R/lab/device/t_loop.py $S/exch/dtu_scan24 --full --out $S/res/u_new \
  > $OUT/u/loop_new.txt 2>&1)
echo "rc=$? after $(( $(date +%s) - t0 )) s"
grep "^== \|^fit \|Warning" $OUT/u/loop_new.txt | cut -c1-300
cp $S/res/u_new/report.json $OUT/u/report_new.json 2>/dev/null
