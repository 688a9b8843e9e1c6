# Lease step a (#59's rows, after the staging calls and a step that installed, e.g. z_all.sh): wtopo's CUDA default
# on the ten-view chair (chair_sparse: it gains the polish; TAG=y) detached, then the ten-view mug (mug_sparse)
# with gsplat at its published 30,000 iterations, wtopo and wtopo without its loop (TAG=w), then waits and scores
# both. Call `TAG=w bash lab/device/w_wait.sh` and `TAG=y WAIT=30 bash lab/device/wait_fits.sh` again (within 30 s
# of each other) while fits are still running.
source lab/device/lease_env.sh
t0=$(date +%s)
[ -f $S/t_installed ] || { lease_install || exit 1; touch $S/t_installed; }
sc=chair_sparse
[ -f $S/exch/$sc/meta.json ] || python3 benchmarks/peers/export.py $sc $S/exch/$sc --name $sc > $S/exch_$sc.log 2>&1
mkdir -p $S/res/$sc
d=$S/res/$sc/wtopo_y
setsid nohup timeout 900 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label wtopo > $d.log 2>&1 < /dev/null &
lease_prepare ${SCENES:-mug_sparse}
for sc in ${SCENES:-mug_sparse}; do
  STAGE=$S bash $D launch "$S/exch/$sc" -- gsplat wtopo wtopo_noloop
done
echo "launched after $(( $(date +%s) - t0 )) s"
TAG=y WAIT=$(( 300 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
TAG=w SYSTEMS="gsplat wtopo wtopo_noloop" WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/w_wait.sh
