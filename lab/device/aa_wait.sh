# The calls after aa_all.sh (within 30 s of the last): waits up to WAIT seconds (default 560) for the background
# d40.sh and AA_PEERS' gsplat and wtopo (default: the mug), printing progress each minute; copies d40's rows into
# $OUT/d40 once it is done and scores each scene (w_wait.sh) once both its systems are.
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-560} ))
n=0
while [ "$(date +%s)" -lt $end ]; do
  d40=0; [ -f $S/bg/d40.rc ] && d40=1
  mug=1; for sc in ${AA_PEERS:-mug}; do [ -f $S/res/$sc/gsplat.rc ] && [ -f $S/res/$sc/wtopo.rc ] || mug=0; done
  [ $d40 = 1 ] && [ $mug = 1 ] && break
  if [ $((n % 6)) = 0 ]; then
    echo "-- $(( $(date +%s) - t0 )) s: d40 $( [ $d40 = 1 ] && echo done || echo "$(ls $S/res/d40/*.rc 2>/dev/null | wc -l) fits done")," \
      "gsplat build $(tail -n 1 $S/bg/build.log 2>/dev/null | cut -c1-80)," \
      "$(for sc in ${AA_PEERS:-mug}; do echo "$sc $(tail -n 1 $S/res/$sc/gsplat.log 2>/dev/null | tr '\r' '\n' | tail -n 1 | cut -c1-80);"; done)"
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
  fi
  n=$((n + 1)); sleep 10
done
if [ -f $S/bg/d40.rc ] && [ ! -f $S/bg/d40.copied ]; then
  mkdir -p $OUT/d40; cp -r $S/d40out/d40/* $OUT/d40/ 2>/dev/null; cp $S/bg/d40.log $OUT/d40/; tail -n 40 $S/bg/d40.log
  touch $S/bg/d40.copied
fi
TAG=aa SYSTEMS="gsplat wtopo" WAIT=5 bash lab/device/w_wait.sh
echo "aa_wait after $(( $(date +%s) - t0 )) s"
