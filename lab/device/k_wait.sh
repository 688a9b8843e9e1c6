# Lease step k, the next calls (within 30 s of the last): the 64-view chair at the `best` preset in the background
# (about 2x the default's 393 s, near gsplat's 757 s), then DTU with 2DGS's distortion weight in the foreground (its
# time shares the GPU with the chair; its quality is the question); every call ends by copying the rows, pictures
# and logs' tails into $OUT/k.
source lab/device/lease_env.sh
t0=$(date +%s)
mkdir -p $OUT/k $S/rows
c=$S/res/chair/wtopo_best
if [ ! -d $c ]; then
  mkdir -p $c
  setsid nohup bash -c "python3 benchmarks/peers/run_wtopo.py $S/exch/chair $c --set preset=best > $c.log 2>&1; \
    echo \$? > $c.rc" > /dev/null 2>&1 &
fi
d=$S/res/dtu_scan24/wtopo_dist1000
if [ ! -d $d ]; then
  mkdir -p $d
  timeout 300 python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $d --set runtime.profile=true \
    --set losses.distortion=1000 > $d.log 2>&1; echo $? > $d.rc
  timeout 90 python3 benchmarks/peers/score.py $S/exch/dtu_scan24 $d --out $S/rows/dtu_scan24_dist1000.json \
    --pictures $S/rows/pic_dtu_dist1000 > /dev/null 2>&1
  cp $d/report.json $OUT/k/report_dist1000.json 2>/dev/null
fi
end=$(( t0 + ${WAIT:-420} ))
while [ "$(date +%s)" -lt $end ] && [ ! -f $c.rc ]; do sleep 10; done
[ -f $c.rc ] && [ ! -f $S/rows/chair_best.json ] && timeout 120 python3 benchmarks/peers/score.py $S/exch/chair $c \
  --out $S/rows/chair_best.json > /dev/null 2>&1
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 160 $f | tr '\n' ' ')"; done
cat $S/rows/*.json > $OUT/k/rows_all.txt 2>/dev/null
for f in $S/res/*/*.log; do echo "==== $f"; tail -c 5000 $f; done > $OUT/k/logs.txt
(cd $S/rows && tar czf $OUT/k/pictures.tgz pic_* 2>/dev/null)
ls $OUT/k
