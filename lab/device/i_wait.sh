# Lease step i, every call after i_all.sh (within 30 s of the last): until WAIT seconds (default 540) have passed,
# start wtopo's warm DTU run (res/dtu_scan24/wtopo_warm, profiled) once the cold one has ended, and score what has
# finished into $OUT/i (rows_all.txt, the reports, the logs' tails in one file), so nothing waits on the next call.
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-540} ))
warm=$S/res/dtu_scan24/wtopo_warm
while [ "$(date +%s)" -lt $end ]; do
  if [ -f $S/res/dtu_scan24/wtopo.rc ] && [ ! -d $warm ]; then
    mkdir -p $warm
    setsid nohup bash -c "python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $warm --set runtime.profile=true \
      > $warm.log 2>&1; echo \$? > $warm.rc" > /dev/null 2>&1 &
    echo "warm DTU run started after $(( $(date +%s) - t0 )) s"
  fi
  left=0; for f in $S/res/*/*.log; do [ -f "${f%.log}.rc" ] || left=$((left + 1)); done
  [ $left -eq 0 ] && [ -d $warm ] && break
  sleep 10
done
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 160 $f | tr '\n' ' ')"; done
mkdir -p $OUT/i $S/rows
for d in $S/res/*/*/; do
  sc=$(basename $(dirname $d)); sy=$(basename $d)
  [ -f $d/run.json ] && [ ! -f $S/rows/${sc}_$sy.json ] && timeout 150 python3 benchmarks/peers/score.py \
    $S/exch/$sc $d --out $S/rows/${sc}_$sy.json --pictures $S/rows/pic_${sc}_$sy > /dev/null 2>&1 &
done
wait
cat $S/rows/*.json > $OUT/i/rows_all.txt 2>/dev/null; cp -r $S/rows/pic_* $OUT/i/ 2>/dev/null
for d in $S/res/*/*/; do
  sc=$(basename $(dirname $d)); sy=$(basename $d)
  f=$(find $d -maxdepth 3 -name report.json | head -1); [ -n "$f" ] && cp $f $OUT/i/report_${sc}_$sy.json
  [ -f ${d%/}.log ] && { echo "==== ${sc}/$sy"; tail -c 6000 ${d%/}.log; } >> $OUT/i/logs.txt
done
(cd $OUT/i && tar czf pack.tgz report_*.json logs.txt pic_* 2>/dev/null; rm -rf report_*.json pic_*)
ls $OUT/i
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
