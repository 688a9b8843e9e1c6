# Lease step l, the next calls (within 30 s of the last): wait up to WAIT seconds for gsplat's chair, then score
# both systems with the held-out renders side by side into $OUT/l (rows.json, chair_renders.png, chair.png).
source lab/device/lease_env.sh
t0=$(date +%s)
g=$(ls -d $S/res/chair/gsplat* 2>/dev/null | head -1)
end=$(( t0 + ${WAIT:-540} ))
done_all() {  # gsplat's chair and every wtopo fit of l_all.sh have written their run.json
  [ -f "$g/run.json" ] || return 1
  for d in $S/res/*/wtopo_l*/; do [ -f "$d/run.json" ] || return 1; done
}
while [ "$(date +%s)" -lt $end ] && ! done_all; do sleep 10; g=$(ls -d $S/res/chair/gsplat* 2>/dev/null | head -1); done
for d in $S/res/*/wtopo_l*/; do echo "$d $([ -f $d/run.json ] && echo done || (echo running; tail -n 2 ${d%/}.log))"; done
mkdir -p $OUT/l
if done_all; then
  timeout 200 python3 benchmarks/peers/score.py $S/exch/chair $S/res/chair/wtopo_l*/ $g --out $OUT/l/rows.json \
    --pictures $OUT/l --render-pictures $OUT/l > $OUT/l/score.log 2>&1; tail -n 3 $OUT/l/score.log
  timeout 200 python3 benchmarks/peers/score.py $S/exch/bunny64 $S/res/bunny64/wtopo_l*/ --out $OUT/l/rows_bunny64.json \
    --render-pictures $OUT/l > $OUT/l/score_bunny64.log 2>&1; tail -n 3 $OUT/l/score_bunny64.log
  timeout 200 python3 benchmarks/peers/score.py $S/exch/dtu_scan24 $S/res/dtu_scan24/wtopo_l*/ \
    --out $OUT/l/rows_dtu.json > $OUT/l/score_dtu.log 2>&1; tail -n 3 $OUT/l/score_dtu.log
else
  echo "still running after $(( $(date +%s) - t0 )) s: call l_wait.sh again"; ls $S/res/chair
fi
