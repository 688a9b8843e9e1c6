# Lease step v (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd, .stage/dtu_raw and
# .stage/base = `git archive` of f9f59e3): the graphed loss terms' CUDA tests, then DTU at the CUDA default as a
# user runs it (benchmarks/peers/run_wtopo.py: wall time images to mesh, peak memory, masked held-out PSNR), once
# plain and once with runtime.profile=true (the per-stage table), then t_loop.py's windows (wall per iteration).
# A call holds 600 s: split the steps over calls, e.g. V_STEPS="tests fit", then "eager profile", then "loop"
# (the first call also installs, exports DTU and compiles the kernels). V_STEPS picks the steps (default
# "tests fit eager profile loop"; "eager": the same fit with every CUDA graph off; "host": the render's host time
# at 100k surfels, 800 px, eager and replayed (lab/host_raster.py); "losses": bench_losses.py at
# 700 px, graphed and eager, each term, the section's kernels by device time, then the per-pixel terms alone (#60's
# goal 3); "base": f9f59e3's plain fit).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_dtu || exit 1
mkdir -p $OUT/v
echo "installed and exported after $(( $(date +%s) - t0 )) s"
R=$PWD
summary() { python3 - "$1" <<'PY'
import json, sys
r = json.load(open(sys.argv[1] + "/run.json"))
print({k: r.get(k) for k in ("wall_s", "peak_gpu_bytes", "iterations", "surfels", "own_report")})
PY
}
for step in ${V_STEPS:-tests fit eager profile loop}; do
  case $step in
  tests) (cd /tmp && timeout 200 python3 -m pytest -q -p no:cacheprovider \
      $R/tests/test_pixel_terms.py $R/tests/test_raster_graph.py $R/tests/test_rasterize_paths.py 2>&1 | tail -n 6
    timeout 150 python3 -m pytest -q -p no:cacheprovider $R/tests/test_adam.py $R/tests/test_bridge.py \
      $R/tests/test_cuda_equality.py 2>&1 | tail -n 6
    timeout 60 python3 $R/benchmarks/bench_optimizer.py --device cuda --surfels 53000 1000000 2>&1 | tail -n 4) ;;
  fit|profile) a=(); [ $step = profile ] && a=(--set runtime.profile=true)
    (cd /tmp && timeout 200 python3 $R/benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $S/res/v_$step "${a[@]}" \
      > $OUT/v/$step.txt 2>&1); echo "$step rc=$?"
    cp $S/res/v_$step/run.json $OUT/v/run_$step.json 2>/dev/null; summary $S/res/v_$step
    cp $S/res/v_$step/run/report.json $OUT/v/report_$step.json 2>/dev/null
    grep -i "warn\|error\|psnr" $OUT/v/$step.txt | cut -c1-300 | head -n 12; tail -n 45 $OUT/v/$step.txt | cut -c1-200 ;;
  host) for g in "" --graph; do (cd /tmp && timeout 120 python3 $R/lab/host_raster.py --device cuda --n 100000 \
      --px 800 --calls 100 --top 12 $g 2>&1 | head -n 14); done ;;
  losses) (cd $R/benchmarks && timeout 200 python3 bench_losses.py --device cuda --resolution 700 --views 16 \
      --kernels ${V_KERNELS:-20} 2>&1 | tail -n 50
    timeout 150 python3 bench_losses.py --device cuda --resolution 700 --views 16 --section-only --pixel-terms \
      --kernels ${V_KERNELS:-20} 2>&1 | tail -n 28) ;;
  eager) (cd /tmp && timeout 200 python3 $R/lab/device/eager_fit.py $S/exch/dtu_scan24 $S/res/v_eager \
      > $OUT/v/eager.txt 2>&1); echo "eager rc=$?"
    cp $S/res/v_eager/run.json $OUT/v/run_eager.json 2>/dev/null; summary $S/res/v_eager; tail -n 5 $OUT/v/eager.txt ;;
  base) [ -d $S/base_site/wtopo ] || python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir \
      --target $S/base_site .stage/base > $S/base_install.log 2>&1 || { tail -5 $S/base_install.log; continue; }
    (cd /tmp && PYTHONPATH=$S/base_site:$PYTHONPATH timeout 250 python3 $R/benchmarks/peers/run_wtopo.py \
      $S/exch/dtu_scan24 $S/res/v_base > $OUT/v/base.txt 2>&1); echo "base rc=$?"
    cp $S/res/v_base/run.json $OUT/v/run_base.json 2>/dev/null; summary $S/res/v_base; tail -n 5 $OUT/v/base.txt | cut -c1-200 ;;
  loop) (cd /tmp && timeout 200 python3 $R/lab/device/t_loop.py $S/exch/dtu_scan24 --out $S/res/v_loop \
      > $OUT/v/loop.txt 2>&1); echo "loop rc=$?"
    grep "^== \|^fit \|Warning" $OUT/v/loop.txt | cut -c1-300 ;;
  esac
  echo "$step done after $(( $(date +%s) - t0 )) s"
done
