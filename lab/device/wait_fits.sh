# The calls after a lease step's detached fits (within 30 s of the last): TAG=m (m_all.sh) or n (n_all.sh). Waits up
# to WAIT seconds for every $S/res/SCENE/wtopo_TAG* result, then scores each scene's into $OUT/TAG/rows_SCENE.json
# (PICTURES=SCENE: that scene's held-out renders and errors as well, SCENE_renders.png; PAR=1: the scenes scored at once;
# SCORE_TIMEOUT: seconds a scene's scoring may take, 100).
source lab/device/lease_env.sh
t0=$(date +%s)
end=$(( t0 + ${WAIT:-540} ))
shopt -s nullglob  # no result folder at all (every launch failed): nothing to wait for
done_all() {
  # a fit that ended without its result (a chain's .rc, lab/device/bias_all.sh) counts as done: its log says why
  for d in $S/res/*/wtopo_${TAG:-m}*/; do [ -f "$d/run.json" ] || [ -f "${d%/}.rc" ] || return 1; done
}
while [ "$(date +%s)" -lt $end ] && ! done_all; do sleep 10; done
for d in $S/res/*/wtopo_${TAG:-m}*/; do echo "$d $([ -f $d/run.json ] && echo done || (echo running; tail -n 2 ${d%/}.log))"; done
mkdir -p $OUT/${TAG:-m}
if done_all; then
  # a call brings back a limited number of files: the rows only, the logs stay on the machine
  for sc in $(ls $S/res); do
    ls -d $S/res/$sc/wtopo_${TAG:-m}*/ > /dev/null 2>&1 || continue
    [[ " ${SKIP:-} " == *" $sc "* ]] && continue  # SKIP="SCENE ...": scored already (by an earlier call)
    pics=(); [ "$sc" = "${PICTURES:-}" ] && pics=(--render-pictures $OUT/${TAG:-m})  # held-out renders of one scene
    timeout ${SCORE_TIMEOUT:-100} python3 benchmarks/peers/score.py $S/exch/$sc $S/res/$sc/wtopo_${TAG:-m}*/ --out $OUT/${TAG:-m}/rows_$sc.json \
      "${pics[@]}" > $S/score_${TAG:-m}_$sc.log 2>&1 &
    [ -n "${PAR:-}" ] || wait  # PAR=1: every scene's scoring at once (16 cores), then their logs
  done
  wait
  for sc in $(ls $S/res); do [ -f $S/score_${TAG:-m}_$sc.log ] && tail -n 2 $S/score_${TAG:-m}_$sc.log | cut -c1-300; done
else
  echo "still running after $(( $(date +%s) - t0 )) s: call wait_fits.sh again"
fi
