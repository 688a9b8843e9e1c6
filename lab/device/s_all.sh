# Lease step s in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw, .stage/old = `git archive e77081a` (the tree before the sweep's and the support rules' kernels),
# .stage/mvs_torch.py and .stage/mesh_policy_numpy.py): #60's initialisation and final mesh on the H200.
#   1. the new kernels on CUDA against the CPU and the references (pytest where the machine has it);
#   2. benchmarks/bench_mvs.py (DTU's 49 views, the Warp score against the torch one),
#      benchmarks/bench_mesh_policy.py --device cuda (the support kernel against e77081a's torch rules) and
#      benchmarks/bench_optimizer.py (the Adam kernel with its finite checks against torch's Adams and the checks
#      the fit made around its multi-tensor step);
#   3. DTU at the CUDA default, profiled, this tree then the old one (RUNS, as p_all.sh), alone on the GPU.
source lab/device/lease_env.sh
t0=$(date +%s)
# a second call on the warm machine (RUNS=old) skips what the first one did
[ -f $S/s_installed ] || { lease_install || exit 1; touch $S/s_installed; }
[ -d $S/old_site/wtopo ] || python3 -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir \
  --target $S/old_site .stage/old > $S/old_install.log 2>&1 || { tail -5 $S/old_install.log; exit 1; }
mkdir -p $OUT/s
[ -n "$SKIP_BENCH" ] || [ -f $S/s_kernels.txt ] || {  # SKIP_BENCH=1: the profiles alone
  if python3 -c "import pytest" 2>/dev/null; then
    timeout 150 python3 -m pytest -q -x tests/test_plane_sweep.py tests/test_vertex_support.py tests/test_mesh_policy.py \
      tests/test_mvs.py tests/test_adam.py 2>&1 | tail -n 5
  else
    echo "no pytest here"
  fi
  timeout 120 python3 benchmarks/bench_mvs.py --device cuda --views 49 --data .stage/dtu_raw/dtu_scan24 --repeats 2 \
    --against .stage/mvs_torch.py
  timeout 150 python3 benchmarks/bench_mesh_policy.py --device cuda --against .stage/mesh_policy_numpy.py
  timeout 60 python3 benchmarks/bench_optimizer.py --device cuda --surfels 100000 1000000
} > $S/s_kernels.txt 2>&1
cp $S/s_kernels.txt $OUT/s/kernels.txt 2>/dev/null
cat $OUT/s/kernels.txt 2>/dev/null | cut -c1-160
# after the benchmarks, which it would share the GPU with (its stereo is the new sweep)
[ -f $S/exch/dtu_scan24/meta.json ] || python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 $S/exch/dtu_scan24 \
  --name dtu_scan24 > $S/exch_dtu.log 2>&1
tail -n 1 $S/exch_dtu.log
echo "tests, benchmarks and export after $(( $(date +%s) - t0 )) s"
for r in ${RUNS:-new old}; do
  [ $(( $(date +%s) - t0 )) -lt 330 ] || { echo "no time left for $r: call again with RUNS=$r"; break; }
  d=$S/res/dtu_scan24/s_$r; mkdir -p $d
  PYTHONPATH=$([ $r = old ] && echo $S/old_site:)$PYTHONPATH timeout 250 python3 benchmarks/peers/run_wtopo.py \
    $S/exch/dtu_scan24 $d --label s_$r --set runtime.profile=true > $d.log 2>&1
  echo "$r rc=$? after $(( $(date +%s) - t0 )) s"; tail -n 2 $d.log | cut -c1-200
  cp $d/run/report.json $OUT/s/report_$r.json 2>/dev/null
  python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(r.get('psnr'), r.get('iterations'), r.get('elapsed_s')); from wtopo.fitting.profiling import format_profile; print(format_profile(r.get('profile')))" $d/run/report.json | head -n 45
done
echo "call ends after $(( $(date +%s) - t0 )) s"
