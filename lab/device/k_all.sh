# Lease step k in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): install; export DTU and the 64-view chair (no peer is built: none runs in this lease); the
# support rules on the GPU against NumPy (bench_mesh_policy.py --device cuda); a first DTU fit compiles Warp's
# kernels (seed 2, scored); then DTU alone at the default, profiled (the final mesh with the rules on the GPU).
# lab/device/k_wait.sh follows: the 64-view chair at `best` (gsplat's wall time) in the background and DTU with
# 2DGS's distortion weight in the foreground.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
for sc in dtu_scan24 chair; do
  [ -f "$S/exch/$sc/meta.json" ] && continue
  src=$sc; [ "$sc" = dtu_scan24 ] && src=.stage/dtu_raw/dtu_scan24
  python3 benchmarks/peers/export.py $src "$S/exch/$sc" --name $sc > $S/exch_$sc.log 2>&1 &
done
wait; tail -n 1 $S/exch_*.log
echo "installed and exported after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/k $S/rows
timeout 200 python3 benchmarks/bench_mesh_policy.py --device cuda > $OUT/k/mesh_policy_gpu.txt 2>&1; tail -n 30 $OUT/k/mesh_policy_gpu.txt
run() {  # NAME ARGS...: one wtopo DTU fit in the foreground, profiled, scored into $S/rows
  local d=$S/res/dtu_scan24/$1; shift; mkdir -p $d
  timeout 300 python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $d --set runtime.profile=true "$@" > $d.log 2>&1
  echo $? > $d.rc; tail -n 45 $d.log | head -n 40
  timeout 90 python3 benchmarks/peers/score.py $S/exch/dtu_scan24 $d --out $S/rows/dtu_scan24_$(basename $d).json \
    --pictures $S/rows/pic_dtu_$(basename $d) > /dev/null 2>&1
  cp $d/report.json $OUT/k/report_$(basename $d).json 2>/dev/null
}
echo "before the compiling run: $(( $(date +%s) - t0 )) s"
run wtopo_seed2 --set runtime.seed=2
echo "after the compiling run: $(( $(date +%s) - t0 )) s"
[ $(( $(date +%s) - t0 )) -lt 420 ] && run wtopo_alone
echo "call ends after $(( $(date +%s) - t0 )) s"
cat $S/rows/*.json > $OUT/k/rows_all.txt 2>/dev/null
