# Lease step e in one device call (the machine is released 30 s after a call ends, so a lease that launches
# jobs and scores them in a later call can lose them): install, lease.sh e, wait for every run, score.
# Carry .stage/usd and .stage/dtu_raw; the p1-p3, gl and small calls come first (lab/device/stage.sh).
S=/root/peers
python3 -m pip install -q --no-index --no-deps --no-compile --target $S/site .stage/usd/*.whl 2>&1 | tail -2
t0=$(date +%s)
S=$S bash lab/device/lease.sh e 2>&1 | tail -12
echo "launched after $(( $(date +%s) - t0 )) s"
end=$(( t0 + ${WAIT:-470} ))
while [ "$(date +%s)" -lt $end ]; do n=$(ls $S/res/*/*.rc 2>/dev/null | wc -l); [ "$n" -ge 6 ] && break; sleep 10; done
echo "fits done after $(( $(date +%s) - t0 )) s"; cat $S/res/*/*.rc | tr '\n' ' '; echo
export PYTHONPATH=$S/site:$PWD/benchmarks/peers/shims LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
mkdir -p $OUT/e/rep $OUT/e/log
for sc in dtu_scan24 bunny_env bunny_env_forward; do
  python3 benchmarks/peers/score.py $S/exch/$sc $S/res/$sc/*/ --out $OUT/e/$sc/rows.json --pictures $OUT/e/$sc 2>&1 | tail -12
  for v in wtopo wtopo_noshells; do
    f=$(find $S/res/$sc/$v -maxdepth 3 -name report.json | head -1); [ -n "$f" ] && cp $f $OUT/e/rep/${sc}_$v.json
    tail -c 2000 $S/res/$sc/$v.log > $OUT/e/log/${sc}_$v.log
  done
done
echo "all done after $(( $(date +%s) - t0 )) s"
