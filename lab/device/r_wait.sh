# Lease step r's calls after r_all.sh (within 30 s of the last): waits for its fits and scores them
# (lab/device/wait_fits.sh, TAG=r); once they are scored, times the fit's plane sweep against the coarse-to-fine one
# on DTU alone on the GPU (lab/c2f_time.py) into $OUT/r/c2f_time.txt.
source lab/device/lease_env.sh
t0=$(date +%s)
TAG=r WAIT=${WAIT:-420} bash lab/device/wait_fits.sh
if ls $OUT/r/rows_*.json > /dev/null 2>&1; then
  timeout 150 python3 lab/c2f_time.py $S/exch/dtu_scan24 --device cuda:0 > $OUT/r/c2f_time.txt 2>&1
  cat $OUT/r/c2f_time.txt
fi
echo "call ends after $(( $(date +%s) - t0 )) s"
