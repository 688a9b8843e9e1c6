# Lease step rp (#60 goal 2, the public path's replays): after the p1, p2 and p3 + gl + small/whl staging calls, in
# one call (carry .stage/usd): install, the replay's tests on CUDA (RP_TESTS: more test files), gsplat's JIT build,
# then bench_rasterize_gpu.py --only rasterizer --profile (800 px, 100k and 1M surfels; the public path with and
# without replays, the fit path, gsplat's rasterization_2dgs, same process) into $OUT/r. RP_GSPLAT=0: no gsplat
# (no build: wtopo's paths alone). RP_TEST_TIMEOUT: seconds for the tests (150). gsplat's build comes back as
# $OUT/ext.tgz; put it in .stage/gsplat_ext/ and carry that folder to skip the build. RP_BENCH: more arguments of the bench (--impls wtopo_fit_path, --sizes ...).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
echo "installed after $(( $(date +%s) - t0 )) s"
R=$PWD
(cd /tmp && timeout ${RP_TEST_TIMEOUT:-150} python3 -m pytest -q -p no:cacheprovider $R/tests/test_rasterize_replay.py ${RP_TESTS:-} \
    2>&1 | tail -n 8)
echo "tests done after $(( $(date +%s) - t0 )) s"
G=()
# gsplat's JIT build from an earlier lease (.stage/gsplat_ext/ext.tgz, brought back as $OUT/ext.tgz): no rebuild
GX=${TORCH_EXTENSIONS_DIR:-$HOME/.cache/torch_extensions}
[ -f .stage/gsplat_ext/ext.tgz ] && mkdir -p $GX && tar xzf .stage/gsplat_ext/ext.tgz -C $GX
if [ "${RP_GSPLAT:-1}" = 1 ]; then
  MAX_JOBS=14 STAGE=$S timeout 300 bash $D build 2>&1 | grep -i gsplat | tail -n 3
  tail -n 2 $S/logs/build_gsplat.log
  echo "gsplat built after $(( $(date +%s) - t0 )) s"
else G=(--no-gsplat); fi
mkdir -p $OUT/r
(cd /tmp && timeout $(( 580 - ($(date +%s) - t0) )) python3 $R/benchmarks/bench_rasterize_gpu.py --device cuda:0 \
    --only rasterizer --profile --repeats ${RP_REPEATS:-10} "${G[@]}" ${RP_BENCH:-} --out $OUT/r 2>&1 | tail -n 60)
echo "done after $(( $(date +%s) - t0 )) s"
[ "${RP_GSPLAT:-1}" = 1 ] && [ ! -f .stage/gsplat_ext/ext.tgz ] && tar czf $OUT/ext.tgz -C $GX . && ls -la $OUT/ext.tgz
