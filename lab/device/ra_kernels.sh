# Lease step ra (#60 goal 2, the pixel kernels): after the p1, p2 and p3 + gl + small/whl staging calls, in one
# call (carry .stage/usd, and .stage/gsplat_ext where an earlier lease brought gsplat's build back): install, the
# rasterizer's CUDA tests, gsplat (JIT build or the staged one), bench_rasterize_gpu.py --only rasterizer --profile
# for wtopo's public and fit paths beside gsplat into $OUT/r, then the fit path again for each register cap of the
# backward pixel kernel in RA_CAPS (the installed copy's BWD_MAX_REGS rewritten) into $OUT/r_cap<N>. RA_PATCHES:
# patch files applied in turn before the caps, the fit path timed after each into $OUT/r_<patch name>; e.g. the
# shared-memory staging of the branch kern: git diff main kern -- kernels wtopo > lab/device/ra_stage.patch, then
# RA_PATCHES=lab/device/ra_stage.patch RA_REPEATS=5 bash lab/device/ra_kernels.sh (about 330 s of device time).
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
echo "installed after $(( $(date +%s) - t0 )) s"
R=$PWD
GX=${TORCH_EXTENSIONS_DIR:-$HOME/.cache/torch_extensions}
[ -f .stage/gsplat_ext/ext.tgz ] && mkdir -p $GX && tar xzf .stage/gsplat_ext/ext.tgz -C $GX
# gsplat's build beside the tests (nvcc on the CPUs while the tests use the GPU)
(MAX_JOBS=12 STAGE=$S timeout 300 bash $D build > $S/ra_build.log 2>&1) &
(cd /tmp && timeout ${RA_TEST_TIMEOUT:-240} python3 -m pytest -q -p no:cacheprovider -x \
    $R/tests/test_rasterize_stability.py $R/tests/test_cuda_equality.py $R/tests/test_rasterize_paths.py \
    $R/tests/test_rasterize.py 2>&1 | tail -n 15)
echo "tests done after $(( $(date +%s) - t0 )) s"
wait
grep -i gsplat $S/ra_build.log | tail -n 3
tail -n 2 $S/logs/build_gsplat.log
echo "gsplat ready after $(( $(date +%s) - t0 )) s"
bench() {  # out-folder, more arguments
  local o=$1; shift
  mkdir -p $OUT/$o
  (cd /tmp && timeout $(( 590 - ($(date +%s) - t0) )) python3 $R/benchmarks/bench_rasterize_gpu.py --device cuda:0 \
      --only rasterizer --profile --repeats ${RA_REPEATS:-10} --out $OUT/$o "$@" 2>&1 \
      | grep -v "^ *0\.0[0-9][0-9] ms" | tail -n ${RA_TAIL:-40})
  echo "bench $o done after $(( $(date +%s) - t0 )) s"
}
bench r --impls wtopo_public wtopo_fit_path
[ -f .stage/gsplat_ext/ext.tgz ] || { tar czf $OUT/ext.tgz -C $GX . && ls -la $OUT/ext.tgz; }
for p in ${RA_PATCHES:-}; do  # cumulative: each patch on the tree before it, the kernels copied into the install
  patch -p1 < $p | tail -n 1 && cp kernels/*.py $S/site/wtopo/kernels/ && cp wtopo/*.py $S/site/wtopo/ \
    && cp wtopo/rasterize/*.py $S/site/wtopo/rasterize/
  RA_TAIL=14 bench r_$(basename $p .patch) --impls wtopo_fit_path
done
if [ -n "${RA_PATCHES:-}" ]; then  # the patched kernels' CUDA tests
  (cd /tmp && timeout 200 python3 -m pytest -q -p no:cacheprovider -x $R/tests/test_rasterize_stability.py \
      $R/tests/test_cuda_equality.py $R/tests/test_rasterize_paths.py -k "cooperative or rasterize or paths" 2>&1 \
      | tail -n 8)
  echo "patched tests done after $(( $(date +%s) - t0 )) s"
fi
K=$S/site/wtopo/kernels/rasterize_backward.py
for cap in ${RA_CAPS:-}; do
  sed -i "s/^BWD_MAX_REGS = .*/BWD_MAX_REGS = $cap/" $K && grep -n "^BWD_MAX_REGS" $K
  RA_TAIL=14 bench r_cap$cap --impls wtopo_fit_path
done
