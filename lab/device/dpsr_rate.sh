# Lease step (#59): the TopoSurfel authors' DPSR loop's rate alone on the GPU, as published and with
# run_pgsr.py --cache-dpsr-grids, from one short warm-up kept on the machine, with nothing else on the GPU.
# After `PEERS="pgsr_dpsr pgsr_init nvdiffrast diso" bash lab/device/sl.sh stage`, carrying .stage/exch/SCENE:
#   SCENE=torus_sparse bash lab/device/dpsr_rate.sh               (the cached stage: about 7 minutes, warm-up included)
#   SCENE=torus_sparse WHICH=published bash lab/device/dpsr_rate.sh (the next call: the warm-up stays on the machine)
# each its own call, within 30 s of the one before so the machine is still held, and before any launch; each
# mesh stage spends about 160 s before its first iteration (2026-12-06, H100), so both together overran one call.
# Prints, for the mesh stage (cached: the figure that decides), seconds per iteration inside its loop
# (iterations 150-250 on the log's tqdm clock; 250 iterations never densify, from 500), the peak GPU memory of its
# train.py and its time; the results stay in /root/peers/rate/ (not scored: the counts are a check's).
source lab/device/lease_env.sh
sc=${SCENE:-torus_sparse}
[ -f .stage/exch/$sc/meta.json ] || { echo "no .stage/exch/$sc carried"; exit 1; }
which=${WHICH:-cached}
mkdir -p $S/exch $S/rate && rm -rf $S/exch/$sc && cp -r .stage/exch/$sc $S/exch/
run() { python3 benchmarks/peers/run_pgsr.py $S/exch/$sc "$@" --checkout $S/peers/pgsr_dpsr \
          --init-checkout $S/peers/pgsr_init; }
t0=$(date +%s)
if [ "$(cat $S/rate/warm.scene 2>/dev/null)" != "$sc" ]; then
  rm -rf $S/rate/*
  run $S/rate/warm --no-mesh-stage --warmup-iterations 1000 > $S/rate/warm.log 2>&1 \
    || { tail -n 5 $S/rate/warm.log; exit 1; }
  echo $sc > $S/rate/warm.scene
  echo "warm-up (1,000 it.) and its TSDF mesh: $(( $(date +%s) - t0 )) s"
fi
for v in $which; do
  more=(); [ $v = cached ] && more=(--cache-dpsr-grids)
  run $S/rate/$v --from-warmup $S/rate/warm --iterations 250 --mesh-train-args=--mesh_from_iter=100 "${more[@]}" \
    > $S/rate/$v.log 2>&1 || { tail -n 5 $S/rate/$v.log; exit 1; }
  python3 - $S/rate/$v $v <<'EOF'
import json, re, sys
d, name = sys.argv[1], sys.argv[2]
text = open(d + "/log.txt", errors="replace").read().replace("\r", "\n")
at = {}  # iteration -> the tqdm clock (s) the last time it printed it
for m in re.finditer(r"Training progress:.*?\|\s*(\d+)/250 \[(?:(\d+):)?(\d+):(\d+)", text):
    it, h, mm, ss = int(m[1]), int(m[2] or 0), int(m[3]), int(m[4])
    at[it] = 3600 * h + 60 * mm + ss
def rate(a, b):
    a, b = min(at, key=lambda i: abs(i - a)), min(at, key=lambda i: abs(i - b))
    return (at[b] - at[a]) / max(b - a, 1), a, b
run, peak = json.load(open(d + "/run.json")), json.load(open(d + "/peak_train.json"))["peak_gpu_bytes"]
loop = rate(150, 250)
print(f"{name}: {loop[0]:.3f} s/it in the loop (it. {loop[1]}-{loop[2]}); its train.py peaked at "
      f"{peak / 2**30:.2f} GiB and took {run['train_s']:.0f} s")
EOF
done
echo "done after $(( $(date +%s) - t0 )) s"
