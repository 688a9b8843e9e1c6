# Lease step o, a whole lease for the TopoSurfel authors' code at its published counts on DTU (#59): its PGSR warm-up
# (30,000 iterations), and with SYSTEM=pgsr then its DPSR mesh stage (10,000), as its scripts/run_dtu.py does, with
# pgsr_nomesh scored from the warm-up. Nothing else runs beside it (beside other jobs the whole took ~35 minutes at
# the rates measured: more than a session's device time, so by default the warm-up alone).
# Staging first: fetch github:Fan-Treasure/pgsr_dpsr, NVlabs/nvdiffrast, SarahWeiii/diso (and hbb1/* + g-truc/glm
# for stage.sh's peers step), `bash lab/device/stage.sh peers`, then the calls p1, p2, p3 + gl + small (small/whl
# and small/peers) as for every lease; this call carries .stage/usd and .stage/dtu_raw.
# Then `bash lab/device/wait.sh`-style calls (STAGE=/root/peers bash benchmarks/peers/device.sh wait 540) until the
# run ends, and `STAGE=/root/peers bash benchmarks/peers/device.sh score $OUT/o`.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 $S/exch/dtu_scan24 --name dtu_scan24 > $S/exch_dtu.log 2>&1 &
MAX_JOBS=16 STAGE=$S timeout 500 bash $D build 2>&1 | tail -n 8
wait
tail -n 1 $S/exch_dtu.log
echo "built and exported after $(( $(date +%s) - t0 )) s"
# SYSTEM=pgsr_nomesh (the default): PGSR alone at its published 30,000 iterations (about 18 minutes at the 28 it/s
# measured beside other jobs, slower from iteration 7,000 where its multi-view term starts), what one lease can hold
# after its start, staging and builds; SYSTEM=pgsr adds the 10,000-iteration mesh stage (about 18 minutes more at
# 8.5-9.8 it/s), more than a session's 30 minutes of device time.
STAGE=$S bash $D launch "$S/exch/dtu_scan24" -- ${SYSTEM:-pgsr_nomesh}
STAGE=$S bash $D wait $(( 570 - ($(date +%s) - t0) ))
