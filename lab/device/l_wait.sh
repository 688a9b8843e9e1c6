# Lease step l, the next calls (within 30 s of the last): wait up to WAIT seconds for gsplat's chair, then score
# both systems with the held-out renders side by side into $OUT/l (rows.json, chair_renders.png, chair.png).
source lab/device/lease_env.sh
t0=$(date +%s)
g=$(ls -d $S/res/chair/gsplat* 2>/dev/null | head -1)
end=$(( t0 + ${WAIT:-540} ))
while [ "$(date +%s)" -lt $end ] && [ ! -f "$g/run.json" ]; do sleep 10; g=$(ls -d $S/res/chair/gsplat* 2>/dev/null | head -1); done
mkdir -p $OUT/l
if [ -f "$g/run.json" ]; then
  timeout 200 python3 benchmarks/peers/score.py $S/exch/chair $S/res/chair/wtopo_l $g --out $OUT/l/rows.json \
    --pictures $OUT/l --render-pictures $OUT/l > $OUT/l/score.log 2>&1; tail -n 3 $OUT/l/score.log
else
  echo "gsplat still running after $(( $(date +%s) - t0 )) s: call l_wait.sh again"; ls $S/res/chair
fi
