# Lease step z (#60's per-part figures, after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd
# and .stage/dtu_raw): DTU at the CUDA default with runtime.profile=true (the per-stage table), the per-pixel
# losses (bench_losses.py, 700 px), then gsplat's JIT build and the rasterizer against gsplat's
# rasterization_2dgs at 100k and 1M surfels, 800 px (bench_rasterize_gpu.py). Z_STEPS picks the steps (also tests: the public
# rasterize path's and the timeline's tests on CUDA; fit:
# the plain fit; loop: t_loop.py's windows; mesh: the profiled fit's mesh.ply, gzipped, into $OUT/v; capture:
# lab/capture_cost.py, a render graph's recapture by part; gaps: lab/outside_gaps.py, the profiled fit's host time
# outside any section by pair of sections; gil: lab/timeline_gil.py, the timeline's writer beside a
# loop bound by its host).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_dtu || exit 1
echo "installed and exported after $(( $(date +%s) - t0 )) s"
R=$PWD
for step in ${Z_STEPS:-profile losses raster}; do
  case $step in
  fit|profile|losses|host|loop) V_STEPS=$step bash lab/device/v_all.sh 2>&1 | grep -v "^installed" ;;
  tests) (cd /tmp && timeout 200 python3 -m pytest -q -p no:cacheprovider $R/tests/test_rasterize_paths.py \
      $R/tests/test_rasterize.py $R/tests/test_fit_timeline.py $R/tests/test_rasterize_replay.py \
      $R/tests/test_raster_graph.py $R/tests/test_fit_graphs.py 2>&1 | tail -n 6) ;;
  gaps) (cd /tmp && timeout 200 python3 $R/lab/outside_gaps.py $S/exch/dtu_scan24 --stop-at ${Z_GAPS_AT:-5000} \
      --device cuda 2>&1 | tail -n 25) ;;
  capture) (cd /tmp && timeout 150 python3 $R/lab/capture_cost.py 2>&1 | tail -n 8) ;;
  gil) (cd /tmp && timeout 150 python3 $R/lab/timeline_gil.py 2>&1 | tail -n 4) ;;
  mesh) gzip -c $S/res/v_profile/run/mesh.ply > $OUT/v/mesh_profile.ply.gz; ls -la $OUT/v ;;
  raster) MAX_JOBS=14 STAGE=$S timeout 400 bash $D build 2>&1 | grep -i gsplat | tail -n 3
    echo "gsplat built after $(( $(date +%s) - t0 )) s"
    mkdir -p $OUT/r
    (cd /tmp && timeout 240 python3 $R/benchmarks/bench_rasterize_gpu.py --device cuda:0 --only rasterizer loss --profile \
      --out $OUT/r 2>&1 | tail -n 40) ;;
  esac
  echo "$step done after $(( $(date +%s) - t0 )) s"
done
