# Lease step r's calls after r_all.sh (within 30 s of the last): waits for its fits and scores them
# (lab/device/wait_fits.sh, TAG=r); once they are scored, with the GPU idle, into $OUT/r/gpu_bench.txt: the fit's
# plane sweep (Warp score) against the torch one it replaced (.stage/mvs_torch.py = e77081a's mvs.py) on DTU's
# 49 views (benchmarks/bench_mvs.py), the same on the exchange folder as the fit runs it (lab/sweep_time.py), and
# one crossing of the bridge with Python's
# profile (benchmarks/bench_bridge.py: where a bridged op's host time goes on the H200 since the views changed).
source lab/device/lease_env.sh
t0=$(date +%s)
TAG=r WAIT=${WAIT:-420} bash lab/device/wait_fits.sh
if ls $OUT/r/rows_*.json > /dev/null 2>&1 && [ ! -f $OUT/r/gpu_bench.txt ]; then
  { timeout 150 python3 benchmarks/bench_mvs.py --device cuda --views 49 --data .stage/dtu_raw/dtu_scan24 \
      --repeats 2 --against .stage/mvs_torch.py
    timeout 60 python3 lab/sweep_time.py $S/exch/dtu_scan24 --device cuda:0 --repeats 2
    timeout 120 python3 benchmarks/bench_bridge.py --device cuda --resolution 700 --calls 200 --profile; } \
    > $OUT/r/gpu_bench.txt 2>&1
  cat $OUT/r/gpu_bench.txt | cut -c1-200
fi
echo "call ends after $(( $(date +%s) - t0 )) s"
