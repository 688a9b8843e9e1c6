# Lease step aa (2026-12-06, #59 and #60 in one lease; after the p1, p2 and p3 + gl + small/whl staging calls, carry
# .stage/usd and .stage/dtu_raw): first, on the quiet machine, DTU at the CUDA default with runtime.profile=true
# (z_all.sh's profile step: the split of the initial surfels and of the USD timeline); then, all at once in the
# background, (1) d40.sh with AA_D40 (its environment: scenes, variants, seeds; default DTU at seeds 0, 1, 2 as
# shipped) into $S/d40out; (2) each of AA_PEERS (default: the dense mug): export, gsplat's JIT build, then gsplat at
# 30,000 iterations beside wtopo's default (device.sh launch). 2026-12-06 it ran with
#   AA_D40='SCENES="dtu_scan24 bunny_env chair_env mug_torus_env" VARIANTS="-;UNSEEN=0;WINDOW=1" SEEDS=0
#           VARIANTS_dtu_scan24="-;WINDOW=1" SEEDS_dtu_scan24="0 1 2"'
# at 25376d6 (UNSEEN and WINDOW: lab/device/patched_run.py of that commit; both rules rejected, decisions.md). This call then waits like aa_wait.sh until about 570 s have passed; the
# calls after it are `bash lab/device/aa_wait.sh` within 30 s of each other until both are done.
source lab/device/lease_env.sh
t0=$(date +%s)
R=$PWD
lease_dtu || exit 1
echo "installed and exported after $(( $(date +%s) - t0 )) s"
Z_STEPS=profile bash lab/device/z_all.sh 2>&1 | grep -v "^installed"
echo "profile done after $(( $(date +%s) - t0 )) s"
mkdir -p $S/bg
eval "export ${AA_D40:-SEEDS='0 1 2'}"
OUT=$S/d40out FIT_TIMEOUT=1100 setsid nohup bash -c "bash lab/device/d40.sh > $S/bg/d40.log 2>&1; echo \$? > $S/bg/d40.rc" \
  > /dev/null 2>&1 &
P=${AA_PEERS:-mug}
setsid nohup bash -c "for sc in $P; do python3 benchmarks/peers/export.py \$sc $S/exch/\$sc --name \$sc > $S/exch_\$sc.log 2>&1 & done
  MAX_JOBS=10 STAGE=$S timeout 500 bash $D build > $S/bg/build.log 2>&1; wait
  for sc in $P; do STAGE=$S bash $D launch $S/exch/\$sc -- gsplat wtopo; done > $S/bg/launch.log 2>&1" > /dev/null 2>&1 &
sleep 5
WAIT=$(( 570 - ($(date +%s) - t0) )) bash lab/device/aa_wait.sh
