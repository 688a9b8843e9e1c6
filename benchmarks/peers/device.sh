#!/usr/bin/env bash
# The peers benchmark on a GPU machine, in steps (each returns quickly; the fits run in the background):
#
#   STAGE=/tmp/peers bash benchmarks/peers/device.sh install     # site-packages: Warp, Open3D, wheels, wtopo
#   STAGE=/tmp/peers bash benchmarks/peers/device.sh build       # 2DGS's CUDA extensions, gsplat's JIT build
#   STAGE=/tmp/peers bash benchmarks/peers/device.sh launch EXCH_DIR... -- SYSTEM...   # start every (scene, system)
#   STAGE=/tmp/peers bash benchmarks/peers/device.sh wait SECONDS  # until every job ends or SECONDS pass
#   STAGE=/tmp/peers bash benchmarks/peers/device.sh score OUT_DIR # rows.json, table.md, pictures
#
# SYSTEM: wtopo, wtopo_noloop, gsplat, 2dgs, pgsr, pgsr_nomesh (WTOPO_ARGS, GSPLAT_ARGS, TWODGS_ARGS, PGSR_ARGS: extra
# arguments of run_wtopo.py, run_gsplat.py, run_2dgs.py, run_pgsr.py, e.g. WTOPO_ARGS="--set ..." or
# PGSR_ARGS="--warmup-iterations 2000").
# pgsr runs the TopoSurfel authors' code whole (PGSR warm-up, then its DPSR mesh stage) and also writes
# pgsr_nomesh from its warm-up, unless pgsr_nomesh is launched too (then a run of its own, the warm-up twice) or
# PGSR_ARGS="--from-warmup DIR" starts its mesh stage from an earlier pgsr_nomesh result (run_pgsr.py says how).
# PGSR_ARGS="--stop-after=SECONDS" ends pgsr's mesh stage (pgsr_nomesh's warm-up) at a checkpoint, and "--resume"
# goes on with it in the same folder (run_pgsr.py --stop-at / --stop-after / --resume).
# $STAGE holds: big.part* (split xz tar of the unpacked Warp and
# Open3D wheels) and/or whl/*.whl (trimesh, plyfile, gsplat), peers/2dgs (a 2d-gaussian-splatting checkout with
# its submodules: diff-surfel-rasterization with third_party/glm, simple-knn), peers/pgsr_dpsr (Fan-Treasure/pgsr_dpsr
# at its newest commit, with submodules/diff-plane-rasterization and simple-knn), peers/pgsr_init (the same repository
# at de24f1a, plain PGSR, without submodules), peers/nvdiffrast, peers/diso (NVlabs/nvdiffrast, SarahWeiii/diso) and
# exch/NAME (export.py's folders). Each peer is optional: build and launch use what is there.
set -uo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../.." && pwd)"
STAGE=${STAGE:-/tmp/peers}
SITE=$STAGE/site
export PYTHONPATH=$SITE:$HERE/shims${PYTHONPATH:+:$PYTHONPATH}
export TORCH_EXTENSIONS_DIR=$STAGE/torch_ext TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
export PYTHONUNBUFFERED=1
# Open3D links libGL.so.1: machines without it get the glvnd libraries from $STAGE/gl/*.deb (install unpacks them)
[ -d "$STAGE/gl/root" ] && export LD_LIBRARY_PATH=$STAGE/gl/root/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
PY=${PYTHON:-python3}
cmd=$1; shift

case $cmd in
install)
  # site-packages: $STAGE/big.tar.xz.part* (an xz tar of unpacked wheels: Warp, Open3D), $STAGE/whl/*.whl, wtopo
  mkdir -p "$SITE" "$STAGE/logs"
  if ls "$STAGE"/big.part* >/dev/null 2>&1 && [ ! -d "$SITE/warp" ]; then
    cat "$STAGE"/big.part* | xz -d -T0 | tar -x -C "$SITE" || exit 1
  fi
  if [ -d "$STAGE/whl" ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$STAGE"/whl/*.whl
  fi
  if ls "$STAGE"/gl/*.deb >/dev/null 2>&1; then
    for f in "$STAGE"/gl/*.deb; do dpkg -x "$f" "$STAGE/gl/root"; done
    export LD_LIBRARY_PATH=$STAGE/gl/root/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  fi
  $PY -m pip install -q --no-index --no-deps --no-build-isolation --no-cache-dir --upgrade --target "$SITE" "$REPO" \
    > "$STAGE/logs/wtopo_install.log" 2>&1 || { cat "$STAGE/logs/wtopo_install.log"; exit 1; }
  # without Warp staged (lab/device/sl.sh: the peers alone) wtopo does not import, and only the peers can run here
  $PY -c "
import importlib, sys
ok, missing = [], []
for m in ('warp', 'open3d', 'trimesh', 'plyfile', 'wtopo'):
    try:
        ok.append(m + ' ' + getattr(importlib.import_module(m), '__version__', ''))
    except Exception as e:
        missing.append(f'{m} ({type(e).__name__})')
print('imports ok:', ', '.join(ok), '| missing:', ', '.join(missing) or 'none')
sys.exit(1 if missing else 0)"
  ;;
build)
  # the peers' CUDA extensions into $SITE (each only where its checkout is staged), gsplat's JIT build into
  # $TORCH_EXTENSIONS_DIR (needs gsplat in $SITE). simple-knn is one module for 2DGS and PGSR: built once.
  mkdir -p "$SITE" "$STAGE/logs"
  P=$STAGE/peers
  exts=()
  [ -d "$P/2dgs/submodules/diff-surfel-rasterization" ] && exts+=("$P/2dgs/submodules/diff-surfel-rasterization")
  for d in "$P/2dgs/submodules/simple-knn" "$P/pgsr_dpsr/submodules/simple-knn"; do
    [ -d "$d" ] && { exts+=("$d"); break; }
  done
  if [ -d "$P/pgsr_dpsr/submodules/diff-plane-rasterization" ]; then
    # CUDA 13's headers no longer bring in <cstdint> for the rasterizer's uint32_t (as for 2DGS's)
    h=$P/pgsr_dpsr/submodules/diff-plane-rasterization/cuda_rasterizer/rasterizer_impl.h
    grep -q '<cstdint>' "$h" || sed -i '0,/^#include/s//#include <cstdint>\n#include/' "$h"
    exts+=("$P/pgsr_dpsr/submodules/diff-plane-rasterization")
  fi
  [ -d "$P/nvdiffrast" ] && exts+=("$P/nvdiffrast")
  [ -d "$P/diso" ] && exts+=("$P/diso")
  for d in "${exts[@]}"; do
    ext=$(basename "$d")
    (cd "$d" && FORCE_CUDA=1 $PY -m pip install --no-index --no-deps --no-build-isolation --no-cache-dir \
       --target "$SITE" . > "$STAGE/logs/build_$ext.log" 2>&1; echo "build $ext: rc $?") &
  done
  if $PY -c "import gsplat" 2>/dev/null; then
  ($PY -c "
import torch, gsplat
from gsplat import rasterization_2dgs
m = torch.zeros(1, 3, device='cuda'); m[:, 2] = 2
q = torch.tensor([[1., 0, 0, 0]], device='cuda'); s = torch.full((1, 3), .1, device='cuda')
o = torch.ones(1, device='cuda'); c = torch.ones(1, 3, device='cuda')
K = torch.tensor([[[50., 0, 32], [0, 50, 32], [0, 0, 1]]], device='cuda')
out = rasterization_2dgs(m, q, s, o, c, torch.eye(4, device='cuda')[None], K, 64, 64)
print('gsplat', gsplat.__version__, 'ok', float(out[1].sum()))
" > "$STAGE/logs/build_gsplat.log" 2>&1; echo "build gsplat: rc $?") &
  fi
  wait
  tail -n 3 "$STAGE"/logs/build_*.log
  for m in diff_surfel_rasterization simple_knn._C diff_plane_rasterization nvdiffrast.torch diso; do
    $PY -c "import torch, $m" 2>/dev/null && echo "import $m: ok" || echo "import $m: MISSING"
  done
  ;;
launch)
  # SERIAL=1: one job after another in one background chain (clean timings); else all at once
  ex=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do ex+=("$1"); shift; done; shift
  chain=""
  mkdir -p "$STAGE/res" "$STAGE/logs"
  for e in "${ex[@]}"; do
    name=$(basename "$e")
    for s in "$@"; do
      out=$STAGE/res/$name/$s
      nomesh=""
      case $s in
        wtopo) c=("$PY" "$HERE/run_wtopo.py" "$e" "$out" ${WTOPO_ARGS:-}) ;;
        wtopo_noloop) c=("$PY" "$HERE/run_wtopo.py" "$e" "$out" --no-loop ${WTOPO_ARGS:-}) ;;
        gsplat) c=("$PY" "$HERE/run_gsplat.py" "$e" "$out" ${GSPLAT_ARGS:-}) ;;
        2dgs) c=("$PY" "$HERE/run_2dgs.py" "$e" "$out" --checkout "$STAGE/peers/2dgs" ${TWODGS_ARGS:-}) ;;
        pgsr|pgsr_nomesh)
          c=("$PY" "$HERE/run_pgsr.py" "$e" "$out" --checkout "$STAGE/peers/pgsr_dpsr"
             --init-checkout "$STAGE/peers/pgsr_init" ${PGSR_ARGS:-})
          if [ "$s" = pgsr_nomesh ]; then c+=(--no-mesh-stage)
          elif [[ " $* " != *" pgsr_nomesh "* && " ${PGSR_ARGS:-} " != *"--from-warmup"*
                  && " ${PGSR_ARGS:-} " != *"--resume"* && " ${PGSR_ARGS:-} " != *"--stop-a"* ]]; then  # --stop-at, --stop-after
            nomesh=$STAGE/res/$name/pgsr_nomesh
            c+=(--nomesh-out "$nomesh"); rm -rf "$nomesh" "$nomesh.rc"
          fi ;;
        *) echo "unknown system $s"; exit 2 ;;
      esac
      rm -f "$out.rc"
      # --resume goes on with the stopped run in $out (its split.json and checkpoint)
      [[ $s = pgsr* && " ${PGSR_ARGS:-} " = *" --resume "* ]] || rm -rf "$out"
      mkdir -p "$out"
      job="$(printf '%q ' "${c[@]}") > $out.log 2>&1; echo \$? > $out.rc"
      if [ -n "$nomesh" ]; then  # the warm-up's own result is a job of its own to wait on, ending with pgsr's
        echo "written by $name/pgsr beside it (--nomesh-out): its log is $out.log" > "$nomesh.log"
        job="$job; cp $out.rc $nomesh.rc"
      fi
      : > "$out.log"  # there at once: a wait right after the launch finds the job
      if [ -n "${SERIAL:-}" ]; then chain="${chain:+$chain; }$job"; echo "queued $name/$s"; continue; fi
      setsid nohup bash -c "$job" >/dev/null 2>&1 &
      echo "launched $name/$s"
    done
  done
  [ -n "$chain" ] && setsid nohup bash -c "$chain" >/dev/null 2>&1 &
  ;;
wait)
  # until every launched job has its .rc; returns at once when none was launched (a fresh machine)
  shopt -s nullglob
  logs=("$STAGE"/res/*/*.log)
  [ ${#logs[@]} -gt 0 ] || { echo "no jobs under $STAGE/res (machine restarted?)"; exit 3; }
  end=$(( $(date +%s) + ${1:-540} ))
  while [ "$(date +%s)" -lt $end ]; do
    left=0
    for log in "$STAGE"/res/*/*.log; do [ -f "${log%.log}.rc" ] || left=$((left + 1)); done
    [ $left -eq 0 ] && break
    sleep 10
  done
  for log in "$STAGE"/res/*/*.log; do
    echo "== $log rc=$(cat "${log%.log}.rc" 2>/dev/null || echo running)"; tail -c 600 "$log"; echo
  done
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv
  ;;
score)
  out=$1; mkdir -p "$out"
  for d in "$STAGE"/res/*/; do
    name=$(basename "$d")
    ex=$(ls -d "$STAGE"/exch/"$name" 2>/dev/null || true)
    [ -n "$ex" ] || { echo "no exchange folder for $name"; continue; }
    $PY "$HERE/score.py" "$ex" "$d"/*/ --out "$out/rows.json" --pictures "$out" || echo "score $name failed"
  done
  $PY "$HERE/table.py" "$out/rows.json" > "$out/table.md"; cat "$out/table.md"
  ;;
*) echo "unknown step $cmd"; exit 2 ;;
esac
