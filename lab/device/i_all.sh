# Lease step i in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): install; export chair, chair_sparse, mug_torus_env and DTU while gsplat's JIT build runs; gsplat
# at its 30,000 iterations on chair, chair_sparse and mug_torus_env (the table's rows still below its count);
# wtopo on DTU at the CUDA default, profiled, twice: on a cold Warp kernel cache (what a fresh machine pays, as
# every earlier DTU figure did) and then warm (what every later run pays; gsplat's own JIT build is outside its
# time). On the side, the Adam step against torch's (bench_optimizer.py). Then lab/device/i_wait.sh.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare chair chair_sparse mug_torus_env dtu_scan24
echo "exported and built after $(( $(date +%s) - t0 )) s"
for sc in chair chair_sparse mug_torus_env; do STAGE=$S bash $D launch "$S/exch/$sc" -- gsplat; done
WTOPO_ARGS="--set runtime.profile=true" STAGE=$S bash $D launch "$S/exch/dtu_scan24" -- wtopo
mkdir -p $OUT/i
timeout 120 python3 benchmarks/bench_optimizer.py --device cuda --surfels 100000 1000000 > $OUT/i/optimizer_gpu.txt 2>&1
cat $OUT/i/optimizer_gpu.txt
WAIT=$(( 420 - ($(date +%s) - t0) )) bash lab/device/i_wait.sh
