# Lease step r in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw, .stage/exch/bunny64 and .stage/mvs_torch.py), all fits side by side (quality, not time):
#   #60: DTU at seeds 0 and 1 with the plane sweep's score in Warp kernels (wtopo/plane_sweep.py; the same
#   points as the torch score it replaced on the CPU exchange folders): does DTU's table hold.
#   #59: clone/split by gradient in the co-evolution (lab/coevo_densify.py) again on the 64-view chair and bunny64:
#   lease k2 rejected it while the harness rendered wtopo with the wider 0.71-px filter, which blurs a densified
#   model's smaller surfels more than the default's; now both render with the fit's filter.
# Then lab/device/r_wait.sh (the calls after it) waits, scores, and times both sweeps on DTU alone.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
mkdir -p $S/exch $S/res $OUT/r
cp -r .stage/exch/bunny64 $S/exch/
for sc in chair; do
  python3 benchmarks/peers/export.py $sc $S/exch/$sc --name $sc > $S/exch_$sc.log 2>&1 &
done
python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 $S/exch/dtu_scan24 --name dtu_scan24 > $S/exch_dtu.log 2>&1
wait
tail -q -n 1 $S/exch_*.log | cut -c1-160
echo "exports done after $(( $(date +%s) - t0 )) s"
run() {  # SCENE NAME SCRIPT ARGS...
  local sc=$1 d=$S/res/$1/wtopo_$2 script=$3; shift 3; mkdir -p $d
  setsid nohup timeout 900 python3 $script $S/exch/$sc $d --label $(basename $d) "$@" > $d.log 2>&1 < /dev/null &
}
W=benchmarks/peers/run_wtopo.py
run dtu_scan24 r_default $W
run dtu_scan24 r_default_seed1 $W --set runtime.seed=1
for sc in chair bunny64; do
  run $sc r_default $W
  run $sc r_coevo lab/coevo_densify.py
done
echo "fits launched after $(( $(date +%s) - t0 )) s"
TAG=r WAIT=$(( 570 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
