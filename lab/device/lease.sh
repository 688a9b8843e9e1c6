#!/usr/bin/env bash
# One lease's jobs (lab), after the staging calls (benchmarks/peers.md, "Staging a lease"). S is the stage folder.
#   a [SECONDS]: install; wtopo on DTU alone (profiled), waiting up to SECONDS (default 300) for it to end so its
#                times are clean; then the peers' builds in the foreground
#   b: the concurrent batch of 2026-12-02 (gsplat, wtopo's density variants, a short synchronisation count)
#   c: the next batch: gsplat on bunny64 (masks as alpha) and DTU (per-view PSNR), the authors' code on DTU at
#      its published counts (30,000 + 10,000 iterations: a lease of its own beside these two)
#   d: install and build (gsplat, 2DGS), then at once: gsplat on bunny64 (random background) and DTU, 2DGS on DTU,
#      wtopo on DTU as shipped and with the peers' initial point count (100,000 stereo points, with and without
#      the background shells): every row with its per-view PSNR
#   e: the background shells on DTU, bunny_env and bunny_env_forward (exported on the GPU machine): as shipped
#      (since 2026-12-02e seeded only where the stereo found nothing) and without them (init.background_points=0);
#      lab/device/e_all.sh runs it, waits and scores in one call
#   f: the peers benchmark's new scenes (benchmarks/peers/scenes.py) beside gsplat: lab/device/f_all.sh (install,
#      export on the machine, wtopo and gsplat launched), then lab/device/f_score.sh (wait, score) in later calls
#   g: gsplat at 30,000 steps on bunny_env and chair_env and wtopo on DTU in the profile, three jobs only:
#      lab/device/g_all.sh, then lab/device/f_score.sh
set -uo pipefail
S=${S:-/root/peers}
D=benchmarks/peers/device.sh
case $1 in
a)
  cp -r .stage/small/whl .stage/small/peers "$S"/ && mkdir -p "$S/exch" && cp -r .stage/exch/* "$S/exch/"
  STAGE=$S bash $D install || exit 1
  STAGE=$S WTOPO_ARGS="--set runtime.profile=true" bash $D launch "$S/exch/dtu_scan24" -- wtopo
  end=$(( $(date +%s) + ${2:-300} ))
  while [ ! -f "$S/res/dtu_scan24/wtopo.rc" ] && [ "$(date +%s)" -lt $end ]; do sleep 5; done
  MAX_JOBS=12 STAGE=$S timeout 480 bash $D build
  ;;
b)
  STAGE=$S bash $D launch "$S/exch/bunny64" "$S/exch/dtu_scan24" -- gsplat
  export PYTHONPATH=$S/site:$PWD/benchmarks/peers/shims PYTHONUNBUFFERED=1
  [ -d "$S/gl/root" ] && export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
  job() {  # name scene variant
    out=$S/res/$2/$1; rm -rf "$out" "$out.rc"; mkdir -p "$out"
    setsid nohup bash -c "python3 lab/density_run.py $3 $S/exch/$2 $out > $out.log 2>&1; echo \$? > $out.rc" \
      >/dev/null 2>&1 &
    echo "launched $2/$1"
  }
  job wtopo_d3dgs dtu_scan24 3dgs
  job wtopo_dgrad2 dtu_scan24 grad2
  job wtopo_d3dgs bunny64 3dgs
  job wtopo bunny64 base
  mkdir -p "$S/sync"
  setsid nohup bash -c "python3 lab/sync_count.py $S/exch/dtu_scan24 --set warmup.iterations=400 \
    --set coevolution.iterations=300 > $S/sync/sync.log 2>&1" >/dev/null 2>&1 &
  ;;
d)
  [ -d .stage/small ] && cp -r .stage/small/whl .stage/small/peers "$S"/   # (or copied by an earlier call)
  mkdir -p "$S/exch" && cp -r .stage/exch/* "$S/exch/"
  STAGE=$S bash $D install || exit 1
  export PYTHONPATH=$S/site:$PWD/benchmarks/peers/shims PYTHONUNBUFFERED=1
  [ -d "$S/gl/root" ] && export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
  if [ ! -f "$S/exch/dtu_scan24/meta.json" ] && [ -d .stage/dtu_raw/dtu_scan24 ]; then  # its stereo on the GPU
    rm -rf "$S/exch/dtu_scan24"
    python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 "$S/exch/dtu_scan24" --name dtu_scan24 || exit 1
  fi
  STAGE=$S bash $D launch "$S/exch/dtu_scan24" -- wtopo
  variant() {  # dir label --set ...
    out=$S/res/dtu_scan24/$1; lab=$2; shift 2; rm -rf "$out" "$out.rc"; mkdir -p "$out"
    setsid nohup bash -c "python3 benchmarks/peers/run_wtopo.py $S/exch/dtu_scan24 $out --label '$lab' $* \
      > $out.log 2>&1; echo \$? > $out.rc" >/dev/null 2>&1 &
    echo "launched dtu_scan24/$1"
  }
  variant wtopo_init100k "wtopo (100k stereo points)" --set init.num_points=100000
  variant wtopo_init100k_nobg "wtopo (100k stereo points, no shells)" --set init.num_points=100000 \
    --set init.background_points=0
  MAX_JOBS=14 STAGE=$S timeout 420 bash $D build
  STAGE=$S bash $D launch "$S/exch/bunny64" "$S/exch/dtu_scan24" -- gsplat
  STAGE=$S bash $D launch "$S/exch/dtu_scan24" -- 2dgs
  ;;
e)
  [ -d .stage/small ] && cp -r .stage/small/whl .stage/small/peers "$S"/
  mkdir -p "$S/exch" && { [ -d .stage/exch ] && cp -r .stage/exch/* "$S/exch/"; }
  STAGE=$S bash $D install || exit 1
  export PYTHONPATH=$S/site:$PWD/benchmarks/peers/shims PYTHONUNBUFFERED=1
  [ -d "$S/gl/root" ] && export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
  [ -f "$S/exch/dtu_scan24/meta.json" ] || python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 \
    "$S/exch/dtu_scan24" --name dtu_scan24 || exit 1
  for sc in bunny_env bunny_env_forward; do
    [ -f "$S/exch/$sc/meta.json" ] || python3 benchmarks/peers/export.py $sc "$S/exch/$sc" --name $sc || exit 1
  done
  for sc in dtu_scan24 bunny_env bunny_env_forward; do
    r=$S/res/$sc; mkdir -p $r
    for v in wtopo wtopo_noshells; do
      case $v in
        wtopo) c="benchmarks/peers/run_wtopo.py $S/exch/$sc $r/$v" ;;
        wtopo_noshells) c="benchmarks/peers/run_wtopo.py $S/exch/$sc $r/$v --label 'wtopo (no shells)' --set init.background_points=0" ;;
      esac
      rm -rf $r/$v $r/$v.rc; mkdir -p $r/$v
      setsid nohup bash -c "python3 $c > $r/$v.log 2>&1; echo \$? > $r/$v.rc" >/dev/null 2>&1 &
      echo "launched $sc/$v"
    done
  done
  ;;
c)
  STAGE=$S bash $D launch "$S/exch/bunny64" "$S/exch/dtu_scan24" -- gsplat
  STAGE=$S bash $D launch "$S/exch/dtu_scan24" -- pgsr
  ;;
esac
