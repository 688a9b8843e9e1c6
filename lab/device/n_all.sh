# Lease step n in one device call (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd,
# .stage/dtu_raw and .stage/exch/bunny64), for the next session:
#   #59: the 0.25-px render filter (lease m: the 64-view chair 31.00 -> 31.18 dB, bunny64 31.46 -> 31.62, both
#   meshes closer) on the scenes it has not met on the GPU: the three unmasked scenes, DTU at seeds 0 and 1 and
#   the ten-view chair; and wtopo without its mesh loop on bunny64 and the chair (#59's with / without the loop
#   rows, beside the authors' code with and without its mesh stage), the chair at `best` (about gsplat's wall time);
#   DTU's held-out renders for its view 40.
#   The defaults are rows_2026-12-04l's (seed 0) and rows_2026-12-04m's (DTU seed 1).
#   lab/device/wait_fits.sh (TAG=n) waits and scores.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
mkdir -p $S/exch $S/res $OUT/n
cp -r .stage/exch/bunny64 $S/exch/
for sc in chair chair_sparse bunny_env chair_env mug_torus_env; do
  python3 benchmarks/peers/export.py $sc $S/exch/$sc --name $sc > $S/exch_$sc.log 2>&1 &
done
python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 $S/exch/dtu_scan24 --name dtu_scan24 > $S/exch_dtu.log 2>&1
wait
tail -q -n 1 $S/exch_*.log
echo "exports done after $(( $(date +%s) - t0 )) s"
# #60: the final mesh's host steps on the GPU machine (the near-camera crop now skips cameras away from the mesh)
timeout 150 python3 benchmarks/bench_mesh_policy.py --device cuda > $OUT/n/mesh_policy_gpu.txt 2>&1
tail -n 9 $OUT/n/mesh_policy_gpu.txt
run() {  # SCENE NAME ARGS...
  local sc=$1 d=$S/res/$1/wtopo_$2; shift 2; mkdir -p $d
  setsid nohup timeout 700 python3 benchmarks/peers/run_wtopo.py $S/exch/$sc $d --label $(basename $d) "$@" \
    > $d.log 2>&1 < /dev/null &
}
for sc in bunny_env chair_env mug_torus_env dtu_scan24 chair_sparse; do run $sc n_f025 --set filter_sigma=0.25; done
run dtu_scan24 n_f025_seed1 --set filter_sigma=0.25 --set runtime.seed=1
run bunny64 n_noloop --no-loop
run chair n_noloop --no-loop
run chair n_best --set preset=best  # wtopo at about gsplat's wall time (#59), rendered with the fit's filter
echo "fits launched after $(( $(date +%s) - t0 )) s"
TAG=n PICTURES=dtu_scan24 WAIT=$(( 570 - ($(date +%s) - t0) )) bash lab/device/wait_fits.sh
