# Lease step fw (#60 goal 2, the forward alone), after the p1 and p2 staging calls; one call carrying .stage/p3,
# .stage/gl and .stage/small/whl:
#   mkdir -p /root/peers/whl /root/peers/gl && cp .stage/p3/* /root/peers/ && cp .stage/small/whl/* /root/peers/whl/ \
#     && cp .stage/gl/* /root/peers/gl/ && bash lab/device/fw_bench.sh
# installs Warp, Open3D, the wheels and this tree's wtopo, builds gsplat's JIT (into $S/torch_ext), runs the
# replay's, the bridge's and the rasterizer paths' tests on CUDA, then lab/raster_forward.py --rounds 10 --profile
# (gsplat's rasterization_2dgs and ours alternately, 100k and 1M surfels at 800 px, and the kernel table of each
# forward), then bench_rasterize_gpu.py --only rasterizer (forward and forward + backward, public and fit paths), into
# $OUT/fw.
source lab/device/lease_env.sh
export TORCH_EXTENSIONS_DIR=$S/torch_ext TORCH_CUDA_ARCH_LIST=9.0
t0=$(date +%s)
lease_install || exit 1
MAX_JOBS=14 STAGE=$S timeout 400 bash $D build 2>&1 | grep -i gsplat | tail -n 3
echo "installed and built after $(( $(date +%s) - t0 )) s"
R=$PWD
mkdir -p $OUT/fw
(cd /tmp && timeout 150 python3 -m pytest -q -p no:cacheprovider $R/tests/test_rasterize_replay.py $R/tests/test_bridge.py \
  $R/tests/test_rasterize_paths.py $R/tests/test_raster_graph.py 2>&1 | tail -n 8 | tee $OUT/fw/tests.txt)
echo "tests done after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout 240 python3 $R/lab/raster_forward.py --rounds 10 --profile > $OUT/fw/raster_forward.txt 2>&1)
tail -n 80 $OUT/fw/raster_forward.txt
echo "forward done after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout 200 python3 $R/benchmarks/bench_rasterize_gpu.py --device cuda:0 --only rasterizer \
  --out $OUT/fw 2>&1 | tail -n 30)
echo "bench done after $(( $(date +%s) - t0 )) s"
