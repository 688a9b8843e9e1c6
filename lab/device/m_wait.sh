# Lease step m, the next calls (within 30 s of the last): wait up to WAIT seconds for m_all.sh's fits, then score
# each scene's into $OUT/m/rows_SCENE.json.
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-540} ))
done_all() {
  for d in $S/res/*/wtopo_m*/; do [ -f "$d/run.json" ] || return 1; done
}
while [ "$(date +%s)" -lt $end ] && ! done_all; do sleep 10; done
for d in $S/res/*/wtopo_m*/; do echo "$d $([ -f $d/run.json ] && echo done || (echo running; tail -n 2 ${d%/}.log))"; done
mkdir -p $OUT/m
if done_all; then
  for sc in $(ls $S/res); do
    [ -d $S/res/$sc ] || continue
    timeout 100 python3 benchmarks/peers/score.py $S/exch/$sc $S/res/$sc/wtopo_m*/ --out $OUT/m/rows_$sc.json \
      > $OUT/m/score_$sc.log 2>&1; tail -n 2 $OUT/m/score_$sc.log | cut -c1-400
  done
else
  echo "still running after $(( $(date +%s) - t0 )) s: call m_wait.sh again"
fi
