#!/usr/bin/env bash
# One lease's jobs (lab): after the staging calls. Step "a": install, wtopo DTU alone, then the peers' builds;
# step "b": the concurrent batch (gsplat fixed, density variants, a short sync count). S is the stage folder.
set -uo pipefail
S=${S:-/root/peers}
D=benchmarks/peers/device.sh
case $1 in
a)
  cp -r .stage/small/whl .stage/small/peers "$S"/ && mkdir -p "$S/exch" && cp -r .stage/exch/* "$S/exch/"
  STAGE=$S bash $D install || exit 1
  STAGE=$S SERIAL=1 bash $D launch "$S/exch/dtu_scan24" -- wtopo
  sleep "${2:-45}"
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
esac
