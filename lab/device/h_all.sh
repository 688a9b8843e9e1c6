# Lease step h in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw): install; export chair, chair_sparse, chair_env, mug_torus_env, bunny_env and DTU while gsplat's
# JIT build runs; on the idle GPU the bridge's host cost against the bridge before this session's change
# (benchmarks/bench_bridge.py --against lab/device/bridge_before.py, an untracked copy of the older
# wtopo/_bridge.py) and the per-pixel losses (bench_losses.py, 700 px); then gsplat at its 30,000 iterations on
# chair, chair_sparse and mug_torus_env (the table's rows still below its count) and wtopo at the CUDA default on
# the three unbounded scenes (the per-face view-support rule) and DTU (a scene too: what the rule does to a real
# capture). lab/device/f_score.sh (WAIT, SCORE=1) in the next calls, within 30 s of each other.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare chair chair_sparse chair_env mug_torus_env bunny_env dtu_scan24
echo "exported and built after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/h
timeout 200 python3 benchmarks/bench_bridge.py --device cuda --resolution 700 --calls 200 --profile --trace \
  --against lab/device/bridge_before.py > $OUT/h/bridge_gpu.txt 2>&1
head -n 12 $OUT/h/bridge_gpu.txt
timeout 180 python3 benchmarks/bench_losses.py --device cuda --resolution 700 --views 16 > $OUT/h/losses_gpu.txt 2>&1
tail -n 25 $OUT/h/losses_gpu.txt
echo "benchmarks done after $(( $(date +%s) - t0 )) s"
for sc in chair chair_sparse mug_torus_env; do STAGE=$S bash $D launch "$S/exch/$sc" -- gsplat; done
for sc in chair_env bunny_env mug_torus_env dtu_scan24; do STAGE=$S bash $D launch "$S/exch/$sc" -- wtopo; done
end=$(( t0 + ${WAIT:-560} ))
while [ "$(date +%s)" -lt $end ]; do sleep 10; done
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 160 $f | tr '\n' ' ')"; done
# score what finished in this call: on 2026-12-03 the device tool's reply came late, the machine went back idle
# before the next call, and every run and result on it was lost (rows_2026-12-03i is the rerun of wtopo's three)
for d in $S/res/*/wtopo; do sc=$(basename $(dirname $d)); [ -f $d/run.json ] && timeout 60 python3 \
  benchmarks/peers/score.py $S/exch/$sc $d --out $OUT/h/rows_$sc.json > /dev/null 2>&1 & done; wait
(cd $OUT/h && cat rows_*.json > rows_all.txt 2>/dev/null && rm -f rows_*.json)
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
