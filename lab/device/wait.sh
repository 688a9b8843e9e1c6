#!/bin/bash
# Wait up to SECONDS (default 540) for lab/device/queue.sh's fits, then pack what they wrote
# (report.json, plan.json, rows.json, history.json, the held-out rows and the logs; no meshes) into
# $OUT/results.tgz: one file, so the device tool's limit on the number of returned files is never met.
end=$((SECONDS + ${1:-540}))
while [ $SECONDS -lt $end ] && [ ! -f /root/stage/ALLDONE ]; do sleep 15; done
echo "reports: $(find /root/stage /root/repo/runs -name report.json 2>/dev/null | wc -l); all done: $([ -f /root/stage/ALLDONE ] && echo yes || echo no)"
# lines queue.sh ran a second time (line number from 0 and the first exit status), and any still failed
[ -s /root/stage/retried.txt ] && echo "run again (line, first exit status): $(tr '\n' ' ' < /root/stage/retried.txt)"
failed=$(grep -lv '^0$' /root/stage/rc_* 2>/dev/null | tr '\n' ' ')
[ -n "$failed" ] && echo "exit status not 0 now: $failed"
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
cd /root && find stage repo/runs \( -name report.json -o -name plan.json -o -name rows.json -o -name history.json \
  -o -path 'stage/*.json' -o -name 'log_*.txt' -o -name 'retried.txt' \) 2>/dev/null | tar czf "$OUT/results.tgz" -T -
ls -la "$OUT"
