#!/bin/bash
# Run a list of fits on the device machine, several per GPU, in the background (the device tool's
# calls last at most 10 minutes; the machine stays held while calls follow each other).
#
#   bash lab/device/queue.sh JOBS PARALLEL
#
# JOBS: a file of commands, one fit per line, run from a copy of the tree in /root/repo (made here,
# with the wtopo.kernels link: lab/gpu.md); the lines that wait for a warm-up run last (below). Line i
# runs on GPU (i + floor(i / n)) % n of n GPUs, with OMP_NUM_THREADS=3, PYTHONPATH=/tmp/site:. (where Warp and trimesh were installed), its output in
# /root/stage/log_i.txt, its exit status in /root/stage/rc_i (a killed line runs once more at the end: below). PARALLEL: fits at once over all GPUs (the 32 fits of hard.md gpu_views_rule ran
# 16 at once on two H200s, 8 per GPU, in about 10 minutes). /root/stage/ALLDONE appears at the end.
set -euo pipefail
jobs=$(realpath "$1"); par=${2:-8}
rm -rf /root/repo && mkdir -p /root/repo /root/stage && cp -r . /root/repo/
ln -sfn ../kernels /root/repo/wtopo/kernels
ngpu=$(nvidia-smi -L | wc -l)
# each line in a subshell with the variables exported: a line may be a compound command (SPLIT=1's branches
# wait for their warm-up in a loop), and all of its output goes to its log
# line i goes to GPU (i + floor(i / n)) % n: consecutive lines still fill every GPU, and a list whose variants
# repeat every n lines (4 variants per warm-up on 4 GPUs) no longer puts every fit of one variant on one GPU
# the lines that wait for a warm-up (SPLIT=1's branches) go after every other line, so with PARALLEL under the
# number of lines no waiting branch holds a slot its warm-up needs (lists of several suite_jobs.sh calls
# interleave them); and each line gets its own truth-mesh cache, /root/stage/hc<line> (every suite_jobs.sh call
# numbers its caches from 0, and two fits building one cache at once race)
{ grep -v '^while \[ ! -f' "$jobs" || true; grep '^while \[ ! -f' "$jobs" || true; } |
  awk '{gsub(/\/root\/stage\/hc[0-9]+/, "/root/stage/hc" NR); print}' |
  awk -v n="$ngpu" '{i = NR - 1; printf "export CUDA_VISIBLE_DEVICES=%d OMP_NUM_THREADS=3 PYTHONPATH=/tmp/site:.; ( %s ) > /root/stage/log_%d.txt 2>&1; echo $? > /root/stage/rc_%d\n", (i + int(i / n)) % n, $0, i, i}' \
  > /root/stage/queue.txt
rm -f /root/stage/ALLDONE /root/stage/rc_* /root/stage/retried.txt
# a line that exits non-zero was killed (lab/hard.py records a fit that raises and goes on): in
# hard.md gpu_cup_restart two loop branches died in the final re-mesh's CPU fallback, twelve fits on a GPU.
# Once every line has run, those lines run once more, RETRY_PARALLEL (default 2) at once, their first log
# kept as log_i.first.txt; retried.txt lists them (line numbers from 0) and wait.sh reports them
# (a SPLIT=1 warm-up line ends with its touch, so a killed warm-up exits 0 and is not run again; its
# branches then fail in hard.py, which records them)
retry=${RETRY_PARALLEL:-2}
cat > /root/stage/retry.sh <<'RETRY'
cd /root/repo
i=0
while IFS= read -r line; do
  rc=$(cat /root/stage/rc_$i 2>/dev/null || echo missing)
  if [ "$rc" != 0 ]; then
    echo "$i $rc" >> /root/stage/retried.txt
    cp /root/stage/log_$i.txt /root/stage/log_$i.first.txt 2>/dev/null || true
    printf '%s\n' "$line"
  fi
  i=$((i + 1))
done < /root/stage/queue.txt > /root/stage/retry.txt
RETRY
cd /root/repo
# setsid and all three streams redirected: the device call returns while the queue runs
setsid nohup bash -c "xargs -d '\\n' -P $par -I{} sh -c {} < /root/stage/queue.txt; bash /root/stage/retry.sh; \
  xargs -d '\\n' -P $retry -I{} sh -c {} < /root/stage/retry.txt; touch /root/stage/ALLDONE" \
  > /root/stage/queue.log 2>&1 < /dev/null &
echo "$(wc -l < /root/stage/queue.txt) fits queued on $ngpu GPUs, $par at once (lines killed: once more, $retry at once)"
