# Lease step t in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw and .stage/base = `git archive` of the tree before this change): where a CUDA fit's iteration goes
# (#60's loop), lab/device/t_loop.py on DTU at the CUDA default, and lab/host_raster.py (the rasterizer's host time
# at 100k surfels, 800 px), for each of RUNS (default "new base").
source lab/device/lease_env.sh
t0=$(date +%s)
lease_dtu || exit 1
[ -d $S/base_site/wtopo ] || python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir \
  --target $S/base_site .stage/base > $S/base_install.log 2>&1 || { tail -5 $S/base_install.log; exit 1; }
mkdir -p $OUT/t
tail -n 1 $S/exch_dtu.log
echo "installed and exported after $(( $(date +%s) - t0 )) s"
R=$PWD
for r in ${RUNS:-new base}; do
  PP=$([ $r = base ] && echo $S/base_site:)$PYTHONPATH
  (cd /tmp && PYTHONPATH=$PP timeout 100 python3 $R/lab/host_raster.py --device cuda --n 100000 --px 800 --calls 100 \
    > $OUT/t/host_raster_$r.txt 2>&1; head -n 22 $OUT/t/host_raster_$r.txt)
  (cd /tmp && PYTHONPATH=$PP timeout ${T_TIMEOUT:-300} python3 $R/lab/device/t_loop.py $S/exch/dtu_scan24 \
    --out $S/res/t_$r ${T_ARGS:-} > $OUT/t/loop_$r.txt 2>&1)
  echo "$r rc=$? after $(( $(date +%s) - t0 )) s"
  grep "^== \|^fit " $OUT/t/loop_$r.txt | cut -c1-300
done
echo "call ends after $(( $(date +%s) - t0 )) s"
