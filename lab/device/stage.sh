#!/usr/bin/env bash
# Recreates .stage/, the folder a peers-benchmark lease copies onto the GPU machine (benchmarks/peers.md,
# "Staging a lease"; benchmarks/peers/device.sh says what the machine expects under $STAGE; lab/device/lease.sh
# step a copies .stage/small/whl, .stage/small/peers and .stage/exch/*). What it makes, under $OUT (.stage):
#
#   p1/big.part00 p2/big.part01 p3/big.part02 ...  one xz tar (xz -9) of the unpacked warp-lang 1.19.0 and open3d
#                      0.19.0 (cp312 manylinux x86_64) wheels, minus the Open3D parts listed in O3D_DROP below,
#                      split into parts of at most PART_BYTES (47 MB), one folder each: one part per device call
#                      (a call carries 64 MiB with the 12.2 MiB working tree).
#                      device.sh install: cat big.part* | xz -d | tar -x
#   small/whl/         py3.12 wheels: trimesh, plyfile (latest), gsplat 1.5.3 (PyPI, JIT-built), its pure-python
#                      requirements (jaxtyping, wadler_lindig, rich, markdown_it_py, mdurl, pygments), ninja and
#                      fast_simplification (cp312 manylinux: trimesh's quadric decimation)
#   small/peers/2dgs   hbb1/2d-gaussian-splatting (newest) with submodules/diff-surfel-rasterization (hbb1, newest;
#                      third_party/glm = g-truc/glm at the commit it pins, glm/ headers and copying.txt only) and
#                      submodules/simple-knn (the plain folder of Fan-Treasure/pgsr_dpsr's tree); no assets/
#   small/peers/{pgsr_dpsr,pgsr_init,nvdiffrast,diso}   the TopoSurfel authors' code (peers.md's table); each only
#                      where its mirror is given (optional)
#   usd/               the usd-core wheel, cp312 manylinux x86_64 (latest)
#   gl/                libgl1, libglvnd0, libglx0 .deb (apt-get download: this machine's Debian bookworm)
#   exch/bunny64       export.py's exchange folder (the venv's python; 64 views of 512 px, 14 MB)
#   dtu_raw/dtu_scan24 the raw DTU scene (11 MB) that lease.sh d exports on the GPU machine (its stereo is too slow
#                      on this CPU); EXPORT_DTU=1 writes exch/dtu_scan24 here instead (over 25 minutes)
#   mvs_torch.py       e77081a's wtopo/geometry/mvs.py: the plane sweep's torch score, before the Warp kernels
#   mesh_policy_numpy.py  e77081a's wtopo/geometry/mesh_policy.py: the support rules before their kernel
#   old/               `git archive e77081a`: the tree before both (lab/device/s_all.sh's "old" DTU profile)
#
# Carrying it (64 MiB a call, 12.2 MiB of it the working tree: about 54 MB left): p1; p2; p3 + gl +
# smallpeers/whl (50 MB); usd + exch + dtu_raw (53 MB); small (16 MB) in a call of its own. p3 + small is 63 MB:
# too much for one call.
#
# What lab/device/sl.sh (the peers alone, no Warp) carries instead, made by the steps `o3d`, `smallpeers` and
# `sl_exch` (about 8 minutes with wheels, gl and peers):
#   o3d/big.part00     one xz tar of the unpacked Open3D wheel alone, minus O3D_DROP (39 MB)
#   smallpeers/        small/ without gsplat's wheel (12 MB; needs the steps wheels and peers)
#   exch/SCENE         export.py's folder of each scene in SL_SCENES (default: the nine object scenes; bunny64 is
#                      bunny at 64 views of 512 px), about 40 s each; nine scenes are about 115 MB, so a call
#                      carries a few .stage/exch/SCENE folders, not .stage/exch (lease.sh a's cp -r .stage/exch/*)
#   bash lab/device/stage.sh wheels gl peers o3d smallpeers sl_exch
#
# What lab/device/wgeo.sh (wtopo's fits alone, no peer: no Open3D) carries, made by the step `warp` from p1-p3 (about
# 8 minutes of xz on a busy 2-core machine):
#   w1/big.part00 w2/big.part01 w3/big.part02   an xz tar of warp/ (without warp/tests) and its .dist-info alone,
#                      100.5 MB in parts of 47 MB: three calls, the first with small(peers)/whl, the last (6.5 MB)
#                      with dtu_raw and usd
#
# Usage:  bash lab/device/stage.sh [STEP...]      STEP: big wheels usd gl peers exch o3d smallpeers sl_exch warp
#         (default: wheels usd gl peers exch big)
# Time on this 2-core machine (shared with other work): about 12 minutes in all, nearly all of it `big` (676 s:
# download, xz -9 -T2 of 593 MB to 141 MB, then the import test from the extracted parts); wheels, usd, gl,
# peers take a few seconds each, exch about a minute. Needs network for pip download / apt-get download.
#
# Repositories come from the session's `fetch` tool (a tool call, not a shell command): call, before this script,
#   fetch github:hbb1/2d-gaussian-splatting     fetch github:hbb1/diff-surfel-rasterization
#   fetch github:g-truc/glm                     fetch github:Fan-Treasure/pgsr_dpsr
#   (optional, for the pgsr peer) fetch github:NVlabs/nvdiffrast   fetch github:SarahWeiii/diso
# Each gives a bare git dir /work/.mirror/OWNER+NAME/repo, the default below; override with
#   M_2DGS M_SURFEL M_GLM M_PGSR M_NVDIFFRAST M_DISO (bare git dirs).
# Other settings: OUT (default REPO/.stage), PY (export.py's python, default REPO/.venv/bin/python),
#   PIP (pip for downloads, default REPO/.venv/bin/pip), XZ_THREADS (2), PART_BYTES (47000000),
#   TEST_IMPORT (1: extract the parts and import warp / open3d with a python3.12 venv made in the temp dir;
#   0: skip), KEEP_TMP (1: keep the temp dir).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../.." && pwd)"
OUT=${OUT:-$REPO/.stage}
PY=${PY:-$REPO/.venv/bin/python}
PIP=${PIP:-$REPO/.venv/bin/pip}
XZ_THREADS=${XZ_THREADS:-2}
PART_BYTES=${PART_BYTES:-47000000}
TEST_IMPORT=${TEST_IMPORT:-1}
MIR=/work/.mirror
M_2DGS=${M_2DGS:-$MIR/hbb1+2d-gaussian-splatting/repo}
M_SURFEL=${M_SURFEL:-$MIR/hbb1+diff-surfel-rasterization/repo}
M_GLM=${M_GLM:-$MIR/g-truc+glm/repo}
M_PGSR=${M_PGSR:-$MIR/Fan-Treasure+pgsr_dpsr/repo}
M_NVDIFFRAST=${M_NVDIFFRAST:-$MIR/NVlabs+nvdiffrast/repo}
M_DISO=${M_DISO:-$MIR/SarahWeiii+diso/repo}
WARP_VER=1.19.0
O3D_VER=0.19.0
GSPLAT_VER=1.5.3
PGSR_INIT_REV=de24f1a   # plain PGSR, the warm-up (peers.md)

# Open3D parts that `import open3d`, pipelines.integration.ScalableTSDFVolume,
# geometry.TriangleMesh.simplify_quadric_decimation and t.geometry.RaycastingScene do not need (paths in the
# unpacked wheel). open3d/cuda: __init__.py finds no cuda/pybind* (StopIteration) and falls back to the CPU
# bindings with an ImportWarning (peers.md: "Open3D 0.19.0 (CPU)"). Kept: open3d/cpu/pybind*.so, the bundled
# libc++ / libtbb, visualization/, ml/ (import open3d imports open3d.ml) and _ml3d/ (ml's datasets import it).
O3D_DROP=(
  open3d/cuda                       # CUDA bindings: pybind (802 MB) and open3d_torch_ops.so (34 MB)
  open3d/cpu/open3d_torch_ops.so    # Open3D-ML torch ops (10 MB), loaded only by `import open3d.ml.torch`
  open3d/resources                  # GUI / renderer assets: fonts, filament materials, IBL skyboxes, html (37 MB)
  open3d/ml/tf                      # Open3D-ML's TensorFlow half
  open3d/examples                   # example scripts
  open3d/labextension open3d/nbextension open3d/web_visualizer.py   # Jupyter widget / WebRTC visualizer
  open3d-0.19.0.data                # Jupyter config and extension files for the environment's share/
)

# ignored by the repo's .gitignore: such paths may not travel in a device call's carry, so none are staged
strip_ignored() {
  find "$1" \( -name __pycache__ -o -name '*.egg-info' -o -name build -o -name runs -o -name .pytest_cache \
    -o -name .venv -o -name .hardcache -o -name '*.pyc' -o -name .DS_Store \) -prune -exec rm -rf {} +
}
need_mirror() { has_mirror "$1" || { echo "no mirror at $1 (fetch it first)"; exit 1; }; }
export_tree() {  # MIRROR TREE DEST [PATHSPEC...]: git archive of TREE (REV, or REV:PATH) into DEST. Pathspecs such
  # as ':(exclude)assets' leave folders out (a mirror may lack its largest blobs, e.g. 2DGS's assets/unbounded.gif)
  local m=$1 tree=$2 dest=$3; shift 3
  mkdir -p "$dest"
  # (it names the absent blobs outside the pathspecs too, "error: invalid object", and still succeeds: dropped)
  git --git-dir="$m" archive "$tree" -- "${@:-.}" 2> >(grep -v '^error: invalid object' >&2) | tar -x -C "$dest"
}
has_mirror() { git --git-dir="$1" rev-parse -q --verify HEAD >/dev/null 2>&1; }
pipdl() { "$PIP" download -q "${PIPDL[@]}" "$@" 2>&1 | { grep -v '^WARNING: Location .* is ignored' || true; }; }
PIPDL=(--only-binary=:all: --python-version 3.12 --implementation cp --no-deps
       --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_27_x86_64
       --platform manylinux_2_28_x86_64 --platform manylinux_2_31_x86_64 --platform manylinux_2_34_x86_64)

# the wheels named (pip specs), unpacked into $TMP/un less O3D_DROP, as one xz tar (names sorted: it extracts into
# site-packages) written to $1
wheels_xz() {
  local dest=$1 w p; shift
  mkdir -p "$TMP/dl" "$TMP/un"
  pipdl -d "$TMP/dl" "$@"
  for w in "$TMP"/dl/*.whl; do unzip -q -o "$w" -d "$TMP/un"; done
  for p in "${O3D_DROP[@]}"; do
    [ -e "$TMP/un/$p" ] || { echo "O3D_DROP: $p not in the wheel"; exit 1; }
    rm -rf "${TMP:?}/un/$p"
  done
  du -sh "$TMP/un"
  (cd "$TMP/un" && tar --sort=name --owner=0 --group=0 --numeric-owner -cf - -- *) | xz -9 -T"$XZ_THREADS" > "$dest"
  rm -rf "$TMP/un" "$TMP/dl"
  ls -l "$dest"
}
# export.py's folder of a scene of scenes.py, or bunny64: the built-in bunny at 64 views of 512 px
export_scene() {
  local args=("$1"); [ "$1" = bunny64 ] && args=(bunny --views 64 --resolution 512)
  rm -rf "${OUT:?}/exch/$1"
  (cd "$REPO" && "$PY" benchmarks/peers/export.py "${args[@]}" "$OUT/exch/$1" --name "$1")
}

TMP=$(mktemp -d "${TMPDIR:-/tmp}/stage.XXXXXX")
[ "${KEEP_TMP:-0}" = 1 ] || trap 'rm -rf "$TMP"' EXIT
mkdir -p "$OUT"
# a device call carries the untracked files git does not ignore: .stage must be ignored (it is not in .gitignore)
if [ "$OUT" = "$REPO/.stage" ] && ! git -C "$REPO" check-ignore -q .stage; then
  echo "warning: .stage is not git-ignored, so every device call would carry it: echo /.stage/ >> $REPO/.git/info/exclude"
fi
steps=("$@"); [ ${#steps[@]} -gt 0 ] || steps=(wheels usd gl peers exch big)

for step in "${steps[@]}"; do
  t0=$(date +%s)
  case $step in
  big)
    wheels_xz "$TMP/big.tar.xz" "warp-lang==$WARP_VER" "open3d==$O3D_VER"   # warp/, open3d/, their .dist-info
    rm -rf "$OUT"/p[0-9]*
    split -b "$PART_BYTES" -d -a 2 "$TMP/big.tar.xz" "$TMP/big.part"
    i=1
    for f in "$TMP"/big.part*; do mkdir -p "$OUT/p$i"; mv "$f" "$OUT/p$i/"; i=$((i + 1)); done
    if [ "$TEST_IMPORT" = 1 ] && command -v python3.12 >/dev/null && PYENV_VERSION=${PYENV_VERSION:-3.12.1} python3.12 -V >/dev/null 2>&1; then
      # the device's import path: the parts, extracted, with benchmarks/peers/shims (plotly, dash, addict);
      # open3d's import also needs numpy, scikit-learn, PyYAML, Pillow, pandas, tqdm (in the GPU image)
      mkdir -p "$TMP/site"
      cat "$OUT"/p*/big.part* | xz -d -T"$XZ_THREADS" | tar -x -C "$TMP/site"
      PYENV_VERSION=${PYENV_VERSION:-3.12.1} python3.12 -m venv "$TMP/py312"
      "$TMP/py312/bin/pip" install -q numpy scikit-learn pyyaml pillow pandas tqdm 2>&1 | grep -v '^WARNING: Location' || true
      PYTHONPATH="$TMP/site:$REPO/benchmarks/peers/shims" "$TMP/py312/bin/python" -W ignore::ImportWarning -c "
import numpy as np, open3d as o3d, warp
print('open3d', o3d.__version__, o3d.__DEVICE_API__, '| warp', warp.__version__)
o3d.pipelines.integration.ScalableTSDFVolume(voxel_length=0.01, sdf_trunc=0.04,
    color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
m = o3d.geometry.TriangleMesh.create_sphere(1.0)
print('simplify_quadric_decimation:', len(m.simplify_quadric_decimation(100).triangles), 'triangles')
sc = o3d.t.geometry.RaycastingScene(); sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
d = sc.compute_distance(o3d.core.Tensor(np.zeros((1, 3), np.float32))).numpy()
print('RaycastingScene distance from the centre:', d)
"
      rm -rf "$TMP/site" "$TMP/py312"
    else
      echo "big: import test skipped (TEST_IMPORT=$TEST_IMPORT or no python3.12)"
    fi
    ;;
  warp)
    ls "$OUT"/p[0-9]*/big.part* > /dev/null || { echo "warp: needs the step big's parts"; exit 1; }
    rm -rf "$TMP/wsite" "$OUT"/w[0-9]*; mkdir -p "$TMP/wsite"
    cat "$OUT"/p[0-9]*/big.part* | xz -d -T"$XZ_THREADS" | tar -x -C "$TMP/wsite" --wildcards 'warp/*' 'warp_lang-*'
    (cd "$TMP/wsite" && tar -c --exclude='warp/tests' warp warp_lang-*) | xz -9e -T"$XZ_THREADS" > "$TMP/warp.tar.xz"
    rm -rf "$TMP/wsite"
    split -b "$PART_BYTES" -d -a 2 "$TMP/warp.tar.xz" "$TMP/big.part"
    i=1
    for f in "$TMP"/big.part*; do mkdir -p "$OUT/w$i"; mv "$f" "$OUT/w$i/"; i=$((i + 1)); done
    rm -f "$TMP/warp.tar.xz"
    ;;
  wheels)
    rm -rf "$OUT/small/whl"; mkdir -p "$OUT/small/whl"
    pipdl -d "$OUT/small/whl" trimesh plyfile "gsplat==$GSPLAT_VER" \
      jaxtyping wadler_lindig rich markdown_it_py mdurl pygments ninja fast_simplification
    ;;
  usd)
    rm -rf "$OUT/usd"; mkdir -p "$OUT/usd"
    pipdl -d "$OUT/usd" usd-core
    ;;
  gl)
    rm -rf "$OUT/gl"; mkdir -p "$OUT/gl"
    # apt-get download writes into the current folder; as root it warns that _apt cannot write there (harmless)
    if ! (cd "$OUT/gl" && apt-get download libgl1 libglvnd0 libglx0 > "$TMP/apt.log" 2>&1); then
      cat "$TMP/apt.log"; echo "gl: apt-get download failed, trying deb.debian.org (bookworm)"; rm -f "$OUT"/gl/*.deb
      for p in libg/libglvnd/libgl1_1.6.0-1_amd64.deb libg/libglvnd/libglvnd0_1.6.0-1_amd64.deb \
               libg/libglvnd/libglx0_1.6.0-1_amd64.deb; do
        curl -fsSL -o "$OUT/gl/$(basename "$p")" "https://deb.debian.org/debian/pool/main/$p"
      done
    fi
    ls "$OUT"/gl/libgl1_*.deb "$OUT"/gl/libglvnd0_*.deb "$OUT"/gl/libglx0_*.deb >/dev/null
    ;;
  peers)
    P=$OUT/small/peers; mkdir -p "$P"
    need_mirror "$M_2DGS"; need_mirror "$M_SURFEL"; need_mirror "$M_GLM"; need_mirror "$M_PGSR"
    rm -rf "$P/2dgs"
    export_tree "$M_2DGS" HEAD "$P/2dgs" . ':(exclude)assets' ':(exclude)submodules'
    S=$P/2dgs/submodules/diff-surfel-rasterization
    export_tree "$M_SURFEL" HEAD "$S" . ':(exclude)third_party/glm'
    # glm at the commit diff-surfel-rasterization pins (its gitlink; else glm's newest), headers and licence only
    glm_rev=$(git --git-dir="$M_SURFEL" ls-tree HEAD third_party/glm | awk '{print $3}')
    git --git-dir="$M_GLM" cat-file -e "${glm_rev:-none}^{commit}" 2>/dev/null || glm_rev=HEAD
    export_tree "$M_GLM" "$glm_rev" "$S/third_party/glm" glm copying.txt
    # CUDA 13's headers no longer bring in <cstdint> for the rasterizer's uint32_t (peers.md; device.sh build adds
    # it for PGSR's rasterizer only)
    h=$S/cuda_rasterizer/rasterizer_impl.h
    grep -q '<cstdint>' "$h" || sed -i '0,/^#include/s//#include <cstdint>\n#include/' "$h"
    export_tree "$M_PGSR" HEAD:submodules/simple-knn "$P/2dgs/submodules/simple-knn"
    {
      echo "2d-gaussian-splatting $(git --git-dir="$M_2DGS" rev-parse HEAD) (without assets/)"
      echo "submodules/diff-surfel-rasterization: hbb1/diff-surfel-rasterization $(git --git-dir="$M_SURFEL" rev-parse HEAD)" \
        "(#include <cstdint> added to cuda_rasterizer/rasterizer_impl.h)"
      echo "submodules/diff-surfel-rasterization/third_party/glm: g-truc/glm $(git --git-dir="$M_GLM" rev-parse "$glm_rev") (glm/, copying.txt)"
      echo "submodules/simple-knn: Fan-Treasure/pgsr_dpsr $(git --git-dir="$M_PGSR" rev-parse HEAD):submodules/simple-knn"
    } > "$P/2dgs/STAGED_FROM.txt"
    # the TopoSurfel authors' code (peers.md's table); nvdiffrast and diso only where their mirrors are there
    rm -rf "$P/pgsr_dpsr" "$P/pgsr_init" "$P/nvdiffrast" "$P/diso"
    export_tree "$M_PGSR" HEAD "$P/pgsr_dpsr" . ':(exclude)assets'
    rm -rf "$P/pgsr_dpsr"/submodules/*/third_party/glm/{doc,test,util}
    if git --git-dir="$M_PGSR" cat-file -e "$PGSR_INIT_REV^{commit}" 2>/dev/null; then
      export_tree "$M_PGSR" "$PGSR_INIT_REV" "$P/pgsr_init" . ':(exclude)assets' ':(exclude)submodules'
    else echo "peers: pgsr_init skipped ($PGSR_INIT_REV not in $M_PGSR)"; fi
    if has_mirror "$M_NVDIFFRAST"; then
      export_tree "$M_NVDIFFRAST" HEAD "$P/nvdiffrast" csrc nvdiffrast setup.py pyproject.toml MANIFEST.in LICENSE.txt README.md
    else echo "peers: nvdiffrast skipped (no mirror at $M_NVDIFFRAST)"; fi
    if has_mirror "$M_DISO"; then
      export_tree "$M_DISO" HEAD "$P/diso" diso src setup.py MANIFEST.in LICENSE README.md
    else echo "peers: diso skipped (no mirror at $M_DISO)"; fi
    strip_ignored "$P"
    du -sh "$P"/*
    ;;
  exch)
    rm -rf "$OUT/exch/dtu_scan24"; mkdir -p "$OUT/exch"   # sl_exch's other scenes stay
    export_scene bunny64
    # DTU's initial points are plane-sweep stereo: over 25 minutes on this 2-core CPU (never finished here), seconds
    # on the GPU. Default: the raw scene goes as dtu_raw/dtu_scan24 (11 MB) and lease.sh d exports it on the GPU
    # machine when exch/dtu_scan24/meta.json is absent. EXPORT_DTU=1: export it here instead.
    if [ "${EXPORT_DTU:-0}" = 1 ]; then
      (cd "$REPO" && "$PY" benchmarks/peers/export.py ../shared/data/dtu_scan24 "$OUT/exch/dtu_scan24" --name dtu_scan24)
    else
      rm -rf "$OUT/dtu_raw"; mkdir -p "$OUT/dtu_raw"; cp -r "$REPO/../shared/data/dtu_scan24" "$OUT/dtu_raw/"
    fi
    strip_ignored "$OUT/exch"
    # the plane sweep's torch score and the support rules' NumPy / torch projections before the Warp kernels, and
    # that whole tree (lab/device/s_all.sh and r_wait.sh: bench_mvs.py and bench_mesh_policy.py --against, DTU's
    # profile before)
    (cd "$REPO" && git show e77081a:wtopo/geometry/mvs.py > "$OUT/mvs_torch.py" \
      && git show e77081a:wtopo/geometry/mesh_policy.py > "$OUT/mesh_policy_numpy.py" \
      && rm -rf "$OUT/old" && mkdir -p "$OUT/old" && git archive e77081a | tar -x -C "$OUT/old")
    ;;
  o3d)
    rm -rf "$OUT/o3d"; mkdir -p "$OUT/o3d"
    wheels_xz "$OUT/o3d/big.part00" "open3d==$O3D_VER"
    ;;
  smallpeers)
    [ -d "$OUT/small/whl" ] && [ -d "$OUT/small/peers/2dgs" ] || { echo "smallpeers: run the steps wheels and peers first"; exit 1; }
    rm -rf "$OUT/smallpeers"
    cp -r "$OUT/small" "$OUT/smallpeers"
    rm -f "$OUT"/smallpeers/whl/gsplat-*.whl
    du -sh "$OUT/smallpeers"
    ;;
  sl_exch)
    mkdir -p "$OUT/exch"
    for sc in ${SL_SCENES:-bunny64 chair torus bowl blob_flat mug chair_sparse torus_sparse mug_sparse}; do
      export_scene "$sc"
    done
    strip_ignored "$OUT/exch"
    du -sh "$OUT"/exch/*
    ;;
  *) echo "unknown step $step (big wheels usd gl peers exch o3d smallpeers sl_exch warp)"; exit 2 ;;
  esac
  echo "== $step: $(( $(date +%s) - t0 )) s"
done

du -sh "$OUT"/*/ 2>/dev/null || true; du -sh "$OUT"/small/*/ "$OUT"/small/peers/*/ 2>/dev/null || true
ls -la "$OUT"/p[0-9]*/ 2>/dev/null || true
small_exch=$(du -cb "$OUT/small" "$OUT/exch" "$OUT/dtu_raw" 2>/dev/null | tail -1 | cut -f1 || true)
echo "small + exch + dtu_raw: $small_exch bytes (one device call carries 67108864 with the working tree)"
