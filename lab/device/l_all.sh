# Lease step l in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd):
# #59's 64-view chair, where gsplat renders the held-out views 2.8 dB sharper: gsplat at its 30,000 iterations
# and wtopo at the default side by side (gsplat's run takes about 760 s: lab/device/l_wait.sh waits for it),
# then score.py --render-pictures puts each held-out view's photo beside both renders and their errors.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
lease_prepare chair
STAGE=$S bash $D launch "$S/exch/chair" -- gsplat
d=$S/res/chair/wtopo_l; mkdir -p $d
timeout 400 python3 benchmarks/peers/run_wtopo.py $S/exch/chair $d > $d.log 2>&1; echo "wtopo rc=$? after $(( $(date +%s) - t0 )) s"
WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/l_wait.sh
