# Lease step g in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd and
# .stage/dtu_raw), planned after lease f: fewer jobs at once so that gsplat reaches its 30,000 steps (lease f ran
# eleven jobs and gsplat trained at 11-25 it/s). Install; export bunny_env, chair_env and DTU on the machine while
# gsplat's JIT build runs; then gsplat on the two unbounded scenes (the ROI F1 target) and wtopo on DTU in the
# profile (runtime.profile: the "after" of benchmarks/gpu.md's DTU profile, with the launch and mesh-policy
# changes). Run 2026-12-03 at f324f72, when it also ran lab/shell_consistency.py on DTU and bunny_env (rejected
# and deleted since: design/decisions.md). lab/device/f_score.sh (WAIT, SCORE=1) in the next calls, within
# 30 s of each other.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare bunny_env chair_env dtu_scan24
echo "exported and built after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/g $S/sync
# the per-pixel losses at 700 x 700 px (#60 goal 3), alone on the GPU before the runs start
timeout 180 python3 benchmarks/bench_losses.py --device cuda --resolution 700 --views 16 > $OUT/g/losses_gpu.txt 2>&1
tail -n 25 $OUT/g/losses_gpu.txt
for sc in bunny_env chair_env; do STAGE=$S bash $D launch "$S/exch/$sc" -- gsplat; done
STAGE=$S WTOPO_ARGS="--set runtime.profile=true" bash $D launch "$S/exch/dtu_scan24" -- wtopo
setsid nohup bash -c "python3 lab/sync_count.py $S/exch/dtu_scan24 --set warmup.iterations=400 \
  --set coevolution.iterations=300 > $S/sync/sync.log 2>&1" >/dev/null 2>&1 &
end=$(( t0 + ${WAIT:-560} ))
while [ "$(date +%s)" -lt $end ]; do sleep 10; done
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 160 $f | tr '\n' ' ')"; done
f=$(find $S/res/dtu_scan24/wtopo -maxdepth 3 -name report.json | head -1)
[ -n "$f" ] && cp $f $OUT/g/dtu_profile_report.json
tail -n 45 $S/sync/sync.log > $OUT/g/sync_count.txt 2>/dev/null; tail -n 4 $OUT/g/sync_count.txt
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
