# Lease step d40 (#59: DTU's held-out view 40 over seeds): after the p1, p2 and p3 + gl + small/whl staging calls,
# carry .stage/usd and .stage/dtu_raw. Fits DTU scan24 at the CUDA default for every variant x seed side by side
# on the one GPU (benchmarks/peers/run_wtopo.py, no timeline), scores each (score.py: whole-image PSNR per held-out
# view) and prints one line per fit: the mean and view 40, then every view; lab/train_psnr.py before it: every
# training view's PSNR (are view 40's neighbours 38, 39 and 41 fitted?). Times are not meaningful (fits share
# the GPU). VARIANTS: ";"-separated lists of --set items ("-" is the default; HARD_VIEWS=P installs
# lab/hard_views.py with power P through lab/device/patched_run.py), e.g.
#   VARIANTS="-;HARD_VIEWS=1;losses.distortion=1000" SEEDS="0 1 2" bash lab/device/d40.sh
# SCENES="NAME ..." fits those scenes of benchmarks/peers/export.py instead, all side by side (each exported first if
# missing; training-view PSNR for DTU only; the summary adds ROI F1), e.g. the shells on the unbounded scenes:
#   SCENES="bunny_env chair_env mug_torus_env" VARIANTS="-;init.background_points=0" SEEDS="0" bash lab/device/d40.sh
# VARIANTS_<scene> and SEEDS_<scene> override VARIANTS and SEEDS for that scene.
source lab/device/lease_env.sh
t0=$(date +%s)
R=$PWD
lease_dtu || exit 1
for SC in ${SCENES:-dtu_scan24}; do
  [ -f $S/exch/$SC/meta.json ] || python3 benchmarks/peers/export.py $SC $S/exch/$SC --name $SC > $S/exch_$SC.log 2>&1 &
done
wait
for SC in ${SCENES:-dtu_scan24}; do [ -f $S/exch/$SC/meta.json ] || { tail -n 5 $S/exch_$SC.log; exit 1; }; done
echo "exports ready after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/d40 $S/res/d40
jobs=()
for SC in ${SCENES:-dtu_scan24}; do
vv=VARIANTS_$SC; ss=SEEDS_$SC
IFS=';' read -ra vars <<< "${!vv:-${VARIANTS:--}}"
for v in "${vars[@]}"; do
  tag=default; [ "$v" = "-" ] || tag=$(echo "$v" | tr -c 'a-zA-Z0-9_=.\n' '_' | tr '=' '-')
  for seed in ${!ss:-${SEEDS:-0 1}}; do
    d=$S/res/d40/${SC}_${tag}_s$seed
    a=(--set runtime.seed=$seed --set runtime.usd_every=0 --label "$v seed $seed"); hv=
    [ "$v" = "-" ] || for item in $v; do
      case $item in HARD_VIEWS=*) hv=${item#HARD_VIEWS=} ;; *) a+=(--set "$item") ;; esac
    done
    (cd /tmp && HARD_VIEWS=$hv timeout ${FIT_TIMEOUT:-480} python3 $R/lab/device/patched_run.py $S/exch/$SC $d \
      "${a[@]}" > $d.log 2>&1; echo $? > $d.rc) &
    echo $SC > $d.scene
    jobs+=($d)
  done
done
done
wait
echo "fits done after $(( $(date +%s) - t0 )) s"
for d in "${jobs[@]}"; do
  [ "$(cat $d.rc)" = 0 ] || { echo "$d rc=$(cat $d.rc)"; tail -n 3 $d.log; continue; }
  SC=$(cat $d.scene)
  timeout 120 python3 benchmarks/peers/score.py $S/exch/$SC $d --out $OUT/d40/rows.json > $d.score 2>&1 \
    || tail -n 3 $d.score
done
ok=(); for d in "${jobs[@]}"; do [ "$(cat $d.rc)" = 0 ] && [ "$(cat $d.scene)" = dtu_scan24 ] && ok+=($d); done
[ ${#ok[@]} -gt 0 ] && timeout 200 python3 lab/train_psnr.py $S/exch/dtu_scan24 "${ok[@]}" 2>&1 | tail -n ${#ok[@]}
python3 - $OUT/d40/rows.json <<'PY'
import json, sys
for r in json.load(open(sys.argv[1])):
    v = r.get("psnr_views") or []
    f1 = f"  ROI F1 {r['roi_f1']:.3f}" if r.get("roi_f1") is not None else ""
    print(f"{r['scene']} {r['system']:<40} mean {r['psnr']:.2f}{f1}  view 40 "
          f"{v[5] if len(v) > 5 else float('nan'):.2f}  views {v}")
PY
echo "done after $(( $(date +%s) - t0 )) s"
