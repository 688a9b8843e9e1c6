# Lease step j in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): install; export DTU and the 64-view chair; the support rules on the GPU against NumPy
# (bench_mesh_policy.py --device cuda); a first DTU fit compiles Warp's kernels (seed 2, scored: a fifth DTU
# PSNR); then, alone, DTU at the default (the final mesh's "after", profiled) and with 2DGS's DTU distortion weight
# (losses.distortion=1000, against 100: does DTU's fused depth agree better from view to view, so that the face
# rule keeps more than 57 % of the faces?). Then lab/device/j_wait.sh starts the 64-view chair at wtopo's `best`
# preset (gsplat's 757 s is about twice wtopo's default there: is the 2.8-dB PSNR gap the step count?).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare dtu_scan24 chair
mkdir -p $OUT/j $S/rows
timeout 240 python3 benchmarks/bench_mesh_policy.py --device cuda > $OUT/j/mesh_policy_gpu.txt 2>&1; cat $OUT/j/mesh_policy_gpu.txt
run() {  # NAME ARGS...: one wtopo DTU fit in the foreground, profiled, scored into $S/rows
  local d=$S/res/dtu_scan24/$1; shift; mkdir -p $d
  timeout 300 python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $d --set runtime.profile=true "$@" > $d.log 2>&1
  echo $? > $d.rc; tail -n 45 $d.log | head -n 40
  timeout 90 python3 benchmarks/peers/score.py $S/exch/dtu_scan24 $d --out $S/rows/dtu_scan24_$(basename $d).json \
    --pictures $S/rows/pic_dtu_$(basename $d) > /dev/null 2>&1
}
run wtopo_seed2 --set runtime.seed=2
echo "after the compiling run: $(( $(date +%s) - t0 )) s"
[ $(( $(date +%s) - t0 )) -lt 330 ] && run wtopo_alone
echo "call ends after $(( $(date +%s) - t0 )) s"
cat $S/rows/*.json > $OUT/j/rows_all.txt 2>/dev/null
