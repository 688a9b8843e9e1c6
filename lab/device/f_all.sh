# Lease step f in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): install; export the peers benchmark's new scenes on the machine (benchmarks/peers/scenes.py:
# chair, chair_sparse, chair_env, mug_torus_env; and bunny_env, DTU from its raw folder) while gsplat's JIT build
# runs; the rasterizer against gsplat on the idle GPU (benchmarks/bench_rasterize_gpu.py, $OUT/f/bench); then
# wtopo at the CUDA default on all six (and DTU at the best preset) and gsplat at its 30,000 iterations on the five
# synthetic scenes
# (saving its splats at 7,000 and 15,000 steps: --mesh-only meshes them if the lease ends first). Then it waits
# until WAIT seconds after its start; lab/device/f_score.sh (the next call, within 30 s) waits on and scores.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
SYN="chair chair_sparse chair_env mug_torus_env bunny_env"
lease_prepare $SYN dtu_scan24
echo "exported and built after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/f/bench
(cd benchmarks && timeout 240 python3 bench_rasterize_gpu.py --device cuda:0 --only rasterizer --warmup 3 --repeats 15 \
  --out $OUT/f/bench > $OUT/f/bench/log.txt 2>&1); grep -A40 "^Rasterizer" $OUT/f/bench/log.txt | head -40
echo "benchmark done after $(( $(date +%s) - t0 )) s"
for sc in $SYN dtu_scan24; do STAGE=$S bash $D launch "$S/exch/$sc" -- wtopo; done
for sc in $SYN; do STAGE=$S bash $D launch "$S/exch/$sc" -- gsplat; done
out=$S/res/dtu_scan24/wtopo_best; rm -rf $out $out.rc; mkdir -p $out  # the best preset (6,000 + 4,000 iterations)
setsid nohup bash -c "python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $out --label 'wtopo (best preset)' \
  --set preset=best > $out.log 2>&1; echo \$? > $out.rc" >/dev/null 2>&1 &
end=$(( t0 + ${WAIT:-560} ))
while [ "$(date +%s)" -lt $end ]; do sleep 10; done
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 160 $f | tr '\n' ' ')"; done
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
