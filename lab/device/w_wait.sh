# The calls after w_suite.sh (within 30 s of the last): waits up to WAIT seconds for every launched system of every
# exported scene ($S/res/SCENE/SYSTEM.rc, written by device.sh launch), then scores each finished scene into
# $OUT/$TAG/rows_SCENE.json with its meshes side by side (SCENE.png) and each system's log's end in logs.txt; with
# RENDERS=1 also every held-out view's photo, renders and errors (SCENE_renders.png; a call brings back 8 files). A
# scene is scored once.
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-540} ))
TAG=${TAG:-w}
SYSTEMS=${SYSTEMS:-gsplat wtopo wtopo_noloop}
mkdir -p $OUT/$TAG $S/scored
pending() {
  local n=0
  for sc in $(ls $S/res); do
    [ -f $S/scored/$sc ] && continue
    for s in $SYSTEMS; do [ -d $S/res/$sc/$s ] && [ ! -f $S/res/$sc/$s.rc ] && n=$((n + 1)); done
  done
  echo $n
}
score_finished() {
  for sc in $(ls $S/res); do
    [ -f $S/scored/$sc ] && continue
    local dirs=() busy=0
    for s in $SYSTEMS; do
      [ -d $S/res/$sc/$s ] || continue
      [ -f $S/res/$sc/$s.rc ] || { busy=1; break; }
      dirs+=($S/res/$sc/$s)
    done
    [ $busy = 1 ] || [ ${#dirs[@]} = 0 ] && continue
    timeout 200 python3 benchmarks/peers/score.py $S/exch/$sc "${dirs[@]}" --out $OUT/$TAG/rows_$sc.json \
      --pictures $OUT/$TAG ${RENDERS:+--render-pictures $OUT/$TAG} > $S/score_${TAG}_$sc.log 2>&1
    tail -n 4 $S/score_${TAG}_$sc.log | cut -c1-300
    for d in "${dirs[@]}"; do  # each system's own log's end, for a row that needs explaining (one file a call)
      { echo "== $d"; tail -n 25 $d.log; [ -f $d/log.txt ] && tail -c 3000 $d/log.txt; } >> $OUT/$TAG/logs.txt
    done
    touch $S/scored/$sc
  done
}
while [ "$(date +%s)" -lt $end ] && [ "$(pending)" != 0 ]; do score_finished; sleep 10; done
score_finished
for sc in $(ls $S/res); do for s in $SYSTEMS; do
  [ -d $S/res/$sc/$s ] && echo "$sc/$s rc=$(cat $S/res/$sc/$s.rc 2>/dev/null || echo running) $(tail -n 1 $S/res/$sc/$s.log | cut -c1-160)"
done; done
[ "$(pending)" = 0 ] || echo "still running after $(( $(date +%s) - t0 )) s: call w_wait.sh again"
