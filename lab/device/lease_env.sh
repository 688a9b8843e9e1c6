# Sourced by the lease scripts (f_all.sh, g_all.sh, f_score.sh): the stage folder, the harness's device script and
# the environment the peers' runs need (site-packages, shims, unbuffered logs, the staged libGL).
#   lease_install            usd-core, then device.sh install (Warp, Open3D, wheels, wtopo)
#   lease_dtu                install once, export DTU scan24 from .stage/dtu_raw once
#   lease_prepare SCENE...   export each scene (a name of export.py; dtu_scan24 from .stage/dtu_raw; bunny64) in the
#                            background while gsplat's JIT build runs, then wait for both
S=/root/peers
D=benchmarks/peers/device.sh
export PYTHONPATH=$S/site:$PWD/benchmarks/peers/shims PYTHONUNBUFFERED=1
[ -d "$S/gl/root" ] && export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu

lease_install() {
  mkdir -p $S/exch $S/res
  python3 -m pip install -q --no-index --no-deps --no-compile --target $S/site .stage/usd/*.whl 2>&1 | tail -2
  STAGE=$S bash $D install 2>&1 | tail -3 || return 1
  [ -d "$S/gl/root" ] && export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
  return 0
}

lease_dtu() {
  # install once per machine, export DTU from .stage/dtu_raw once (the t_, u_ and v_ steps)
  [ -f $S/t_installed ] || { lease_install || return 1; touch $S/t_installed; }
  [ -f $S/exch/dtu_scan24/meta.json ] || python3 benchmarks/peers/export.py .stage/dtu_raw/dtu_scan24 \
    $S/exch/dtu_scan24 --name dtu_scan24 > $S/exch_dtu.log 2>&1
}

lease_prepare() {
  for sc in "$@"; do
    [ -f "$S/exch/$sc/meta.json" ] && continue
    # dtu_scan24 from the carried raw scene; bunny64 the built-in bunny at 64 views of 512 px (peers.md's run; or
    # carry .stage/exch/bunny64 into $S/exch, the folder the earlier rows read); any other a name of scenes.py
    args=($sc); [ "$sc" = dtu_scan24 ] && args=(.stage/dtu_raw/dtu_scan24)
    [ "$sc" = bunny64 ] && args=(bunny --views 64 --resolution 512)
    python3 benchmarks/peers/export.py "${args[@]}" "$S/exch/$sc" --name $sc > $S/exch_$sc.log 2>&1 &
  done
  MAX_JOBS=12 STAGE=$S timeout 400 bash $D build 2>&1 | grep -i "gsplat"
  wait
  tail -n 1 $S/exch_*.log
}
