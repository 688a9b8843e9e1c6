# Lease step k2 (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd, .stage/dtu_raw and
# .stage/exch): lab/coevo_densify.py (clone/split by gradient in the first half of the co-evolution) against the
# default, all fits side by side on the GPU (quality, not time): bunny64 both ways, the 64-view chair and DTU
# with the patch (their defaults: rows_2026-12-03k). Each fit is scored as soon as it ends; the call stops waiting
# at DEADLINE seconds (default 370) and copies what is there to $OUT/k2.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
mkdir -p $S/exch $OUT/k2 $S/rows; cp -r .stage/exch/bunny64 $S/exch/
one() {  # SCENE NAME SCRIPT: fit and score in the background
  local d=$S/res/$1/$2; mkdir -p $d
  (timeout 400 python3 $3 $S/exch/$1 $d > $d.log 2>&1; echo $? > $d.rc
   timeout 120 python3 benchmarks/peers/score.py $S/exch/$1 $d --out $S/rows/$1_$2.json > $d.score.log 2>&1) &
}
one bunny64 default benchmarks/peers/run_wtopo.py
one bunny64 coevo lab/coevo_densify.py
for sc in dtu_scan24 chair; do
  src=$sc; [ "$sc" = dtu_scan24 ] && src=.stage/dtu_raw/dtu_scan24
  (python3 benchmarks/peers/export.py $src "$S/exch/$sc" --name $sc > $S/exch_$sc.log 2>&1 && one $sc coevo lab/coevo_densify.py; wait) &
done
end=$(( t0 + ${DEADLINE:-370} ))
while [ "$(date +%s)" -lt $end ] && [ $(ls $S/rows/*.json 2>/dev/null | wc -l) -lt 4 ]; do sleep 5; done
echo "waited until $(( $(date +%s) - t0 )) s"
for f in $S/res/*/*.log; do echo "== $f rc=$(cat ${f%.log}.rc 2>/dev/null || echo running): $(tail -c 200 $f | tr '\n' ' ')"; done
for r in $S/res/*/*/run/report.json; do python3 -c "
import json; r=json.load(open('$r')); print('$r', r.get('surfels'), r.get('elapsed_s'), r.get('psnr'))"; done
cp $S/rows/*.json $OUT/k2/ 2>/dev/null; ls $OUT/k2
