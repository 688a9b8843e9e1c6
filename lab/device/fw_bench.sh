# Lease step fw (#60 goal 2, the forward alone): on a machine staged and built by w_suite.sh (Warp, gsplat's JIT
# build in $S/torch_ext), wtopo installed again from this tree, the replay's and the bridge's tests on CUDA, then
# lab/raster_forward.py --rounds 10 --profile (gsplat's rasterization_2dgs and ours alternately, 100k and 1M
# surfels at 800 px, and the kernel table of each forward). One call: bash lab/device/fw_bench.sh
source lab/device/lease_env.sh
export TORCH_EXTENSIONS_DIR=$S/torch_ext TORCH_CUDA_ARCH_LIST=9.0
t0=$(date +%s)
STAGE=$S bash $D install 2>&1 | tail -n 1
R=$PWD
(cd /tmp && timeout 240 python3 -m pytest -q -p no:cacheprovider $R/tests/test_rasterize_replay.py $R/tests/test_bridge.py \
  $R/tests/test_rasterize_paths.py $R/tests/test_raster_graph.py 2>&1 | tail -n 8)
echo "tests done after $(( $(date +%s) - t0 )) s"
(cd /tmp && timeout 300 python3 $R/lab/raster_forward.py --rounds 10 --profile 2>&1 | tail -n 80)
echo "bench done after $(( $(date +%s) - t0 )) s"
