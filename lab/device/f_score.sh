# Lease step f, the later calls: wait up to WAIT seconds for every run (lab/device/f_all.sh launched them), then,
# with SCORE=1, score what finished into $OUT/f (rows.json, table.md, pictures; wtopo's report.json and each log's
# tail). A gsplat run still training is stopped and meshed from its saved splats with MESH_ONLY=STEP (7000 or 15000),
# each within MESH_S seconds (default 150). Every step has a time limit: on 2026-12-02 (lease f) the meshing of four
# stopped runs outlasted the call and nothing was scored.
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-540} ))
while [ "$(date +%s)" -lt $end ]; do
  left=0; for f in $S/res/*/*.log; do [ -f "${f%.log}.rc" ] || left=$((left + 1)); done
  [ $left -eq 0 ] && break; sleep 10
done
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 200 $f | tr '\n' ' ')"; done
[ -n "${SCORE:-}" ] || exit 0
if [ -n "${MESH_ONLY:-}" ]; then
  for f in $S/res/*/gsplat.log; do
    [ -f "${f%.log}.rc" ] && continue
    d=${f%.log}; sc=$(basename $(dirname $d))
    [ -f $d/splats_$MESH_ONLY.pt ] || continue
    pkill -f "[r]un_gsplat.py $S/exch/$sc $d" ; sleep 2; echo "stopped" > $d.rc
    timeout ${MESH_S:-150} python3 benchmarks/peers/run_gsplat.py $S/exch/$sc $d --mesh-only $MESH_ONLY \
      > ${d}_mesh_only.txt 2>&1 &
  done
  wait
fi
mkdir -p $OUT/f/rep $OUT/f/log
for d in $S/res/*/; do
  sc=$(basename $d)
  ok=(); for r in $d*/; do [ -f $r/run.json ] && ok+=($r); done
  [ ${#ok[@]} -gt 0 ] && timeout 120 python3 benchmarks/peers/score.py $S/exch/$sc "${ok[@]}" \
    --out $OUT/f/rows_$sc.json --pictures $OUT/f 2>&1 | grep -v "^{" | tail -3 &
done
wait
for d in $S/res/*/; do
  sc=$(basename $d)
  f=$(find $d/wtopo -maxdepth 3 -name report.json | head -1); [ -n "$f" ] && cp $f $OUT/f/rep/${sc}_wtopo.json
  for l in $d*.log; do tail -c 3000 $l > $OUT/f/log/${sc}_$(basename $l); done
done
python3 benchmarks/peers/table.py $OUT/f/rows_*.json > $OUT/f/table.md; cat $OUT/f/table.md
# the device returns a few files a call: pack the logs and reports into one
(cd $OUT/f && tar czf logs.tgz log rep && rm -rf log rep)
echo "scored after $(( $(date +%s) - t0 )) s"
