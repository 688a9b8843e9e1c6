# Lease step sl (#59): the peers' runs (2DGS, the authors' code) in fewer calls and less device time than the other
# lease scripts, for a lease short of time. Nothing of wtopo runs on the machine: no Warp is staged, the scenes are
# exported here and carried, and each finished run's result folder comes back in xz parts, to be scored here.
#   here, once (a new checkout: about 8 minutes; fetch the peers' mirrors first, stage.sh says which):
#                bash lab/device/stage.sh wheels gl peers o3d smallpeers sl_exch
#                (.stage/exch/SCENE per scene, bunny64 the bunny at 64 views of 512 px; .stage/o3d/big.part00, an xz
#                tar of the unpacked Open3D 0.19 cp312 wheel, 39 MB: with .stage/gl and .stage/smallpeers one call
#                carries all a peer needs)
#   1. carrying .stage/o3d .stage/gl .stage/smallpeers:   PEERS="2dgs" bash lab/device/sl.sh stage
#      (.stage/smallpeers: .stage/small without gsplat's wheel, which nothing here runs; the carry and the tree must
#      stay under 64 MiB. PEERS: folders of its peers/; the authors' code: "pgsr_dpsr pgsr_init nvdiffrast diso")
#   2. carrying .stage/exch (or the scenes' folders, .stage/exch/SCENE each, to stay under 64 MiB):
#        SCENES="chair torus_sparse" SYSTEMS=2dgs [TWODGS_ARGS=...] bash lab/device/sl.sh launch
#      (a scene's own systems: SCENES="bunny64:pgsr_nomesh chair:2dgs torus_sparse:2dgs")
#   3. within 30 s of each other:   bash lab/device/sl.sh wait   until it says "all results sent"
#   here: bash lab/device/sl.sh unpack /work/.device/N/sl ...   (each call's files_at/sl) unpacks each complete
#         result into .stage/slres/SCENE/SYSTEM; then
#         .venv/bin/python benchmarks/peers/score.py .stage/exch/SCENE .stage/slres/SCENE/* --out rows.json --pictures D
# A result travels as SCENE__SYSTEM__IofN.txz (10 MiB parts, six a call; RESEND=1 sends every part again): its
# run.json, mesh.ply, renders.npz and logs; for pgsr_nomesh the warm-up's TSDF mesh the mesh stage reads in place of
# mesh.ply, which is that mesh again (unpack restores it). The authors' code at its published counts takes
# at least two leases: the warm-up (SYSTEMS=pgsr_nomesh) in one; here
#   bash lab/device/sl.sh warmstage SCENE /work/.device/N/sl ...   groups its result's parts into .stage/warm/K;
# in the next, after step 1, one call per folder .stage/warm/K, carrying it alone:   bash lab/device/sl.sh warm
# then step 2 with SYSTEMS=pgsr FROM_WARMUP=1: each scene's mesh stage starts from its carried warm-up
# (run_pgsr.py --from-warmup; the row counts both stages' time and the larger peak). lab/device/dpsr_rate.sh
# measures its DPSR loop's rate alone, as published and with PGSR_ARGS=--cache-dpsr-grids, after step 1.
# (device.sh splits PGSR_ARGS at spaces: use the = forms, e.g. --mesh-train-args=--mesh_from_iter=200).
# Its loop runs 0.40-0.48 s an iteration alone with its grids cached, so the mesh stage itself takes two leases:
# PGSR_ARGS="--cache-dpsr-grids --stop-after=SECONDS" (or --stop-at=N, N a multiple of the scene's training views)
# ends it at its checkpoint,
# and the wait step sends what --resume needs (split.json's carry) as SCENE__pgsr__split parts; here
#   bash lab/device/sl.sh splitstage SCENE /work/.device/N/sl ...   groups them into .stage/splitin/K (five parts:
#   with the tree, under a call's 64 MiB);
# in the next lease, after step 1, one call per folder, carrying it alone:   bash lab/device/sl.sh splitin
# then step 2 with SYSTEMS=pgsr RESUME=1 and the same PGSR_ARGS (a --stop-after for this lease, or none).
# The warm-up splits the same way, should its 30,000 iterations not fit a lease: SCENES=SCENE:pgsr_nomesh with
# PGSR_ARGS="--stop-after=SECONDS"; SYSTEM=pgsr_nomesh bash lab/device/sl.sh splitstage SCENE ...; next lease,
# splitin, then SCENES=SCENE:pgsr_nomesh RESUME=1 (its finished result is then the warm-up FROM_WARMUP carries).
step=${1:-wait}
set -o pipefail
shopt -s nullglob
complete_parts() {  # $1: SCENE__SYSTEM, then folders: the N parts of one packing in order, or fail
  local key=$1 files m i f want out=()
  shift
  files=($(for d in "$@"; do for f in "$d"/${key}__[0-9]*of[0-9]*.txz; do echo "$f"; done; done \
    | awk -F/ '{print $NF "\t" $0}' | sort -u -k1,1 | cut -f2))
  [ ${#files[@]} -gt 0 ] || return 1
  m=$(basename "${files[0]}" .txz); m=${m##*of}
  [ ${#files[@]} = $((10#$m)) ] || return 1  # missing parts, or parts of two packings
  for i in $(seq 1 $((10#$m))); do
    want=$(printf "%s__%02dof%s.txz" "$key" $i "$m")
    f=$(printf "%s\n" "${files[@]}" | grep -F "/$want" | head -n 1)
    [ -n "$f" ] || return 1
    out+=("$f")
  done
  printf "%s\n" "${out[@]}"
}
unpack_parts() {  # $1: SCENE__SYSTEM, $2: destination folder, then folders: replaces $2 only on a whole unpack
  local key=$1 dest=$2 parts tmp
  shift 2
  parts=($(complete_parts "$key" "$@")) || { echo "${key/__//}: not every part is here"; return 1; }
  mkdir -p "$(dirname "$dest")" && tmp=$(mktemp -d "$(dirname "$dest")/.unpack.XXXX") || return 1
  if cat "${parts[@]}" | xz -d | tar -x -C "$tmp"; then
    rm -rf "$dest" && mv "$tmp" "$dest"
  else
    rm -rf "$tmp"; echo "${key/__//}: unpacking failed"; return 1
  fi
}
if [ "$step" = splitstage ] || [ "$step" = warmstage ]; then
  # here: the parts a later lease carries in, five a folder (with the tree, under a call's 64 MiB): splitstage a
  # stopped run's (SYSTEM=pgsr, or pgsr_nomesh for a stopped warm-up) into .stage/splitin/K, for splitin;
  # warmstage a finished warm-up's result into .stage/warm/K, for warm and FROM_WARMUP
  sc=${2:?SCENE}; shift 2
  if [ "$step" = splitstage ]; then key=${sc}__${SYSTEM:-pgsr}__split; dest=.stage/splitin
  else key=${sc}__pgsr_nomesh; dest=.stage/warm; fi
  parts=($(complete_parts $key "$@")) || { echo "${key//__//}: not every part is here"; exit 1; }
  rm -rf $dest && i=0
  for f in "${parts[@]}"; do
    k=$(printf "$dest/%02d" $((i / 5 + 1))); mkdir -p $k && cp "$f" $k/ && i=$((i + 1))
  done
  ls $dest
  exit 0
fi
if [ "$step" = unpack ]; then
  shift
  for key in $(for d in "$@"; do ls "$d"; done | grep -E '__[0-9]+of[0-9]+\.txz$' | sed -E 's/__[0-9]+of[0-9]+\.txz$//' \
               | sort -u); do
    sc=${key%%__*}; sys=${key#*__}; dest=.stage/slres/$sc/$sys
    unpack_parts "$key" "$dest" "$@" || continue
    [ -f $dest/mesh.ply ] || [ ! -f $dest/warmup/mesh/tsdf_fusion_post.ply ] || cp $dest/warmup/mesh/tsdf_fusion_post.ply $dest/mesh.ply
    echo "$sc/$sys: unpacked into $dest"
  done
  exit 0
fi
source lab/device/lease_env.sh
t0=$(date +%s)
P=$S/slpack
mkdir -p $P/sent
case $step in
stage)
  mkdir -p $S/whl $S/gl $S/peers
  SMALL=${SMALL:-.stage/smallpeers}
  cp .stage/o3d/* $S/ && cp .stage/gl/* $S/gl/ && ls $SMALL/whl/*.whl | grep -v /gsplat- | xargs -I{} cp {} $S/whl/
  for p in ${PEERS:-2dgs}; do cp -r $SMALL/peers/$p $S/peers/; done
  # device.sh install: Open3D, the wheels, the GL libraries (and wtopo's sources, which cannot import without Warp)
  STAGE=$S bash $D install 2>&1 | tail -n 8
  export LD_LIBRARY_PATH=$S/gl/root/usr/lib/x86_64-linux-gnu
  python3 -c "import open3d, trimesh, plyfile; print('open3d', open3d.__version__, 'trimesh', trimesh.__version__)"
  MAX_JOBS=16 STAGE=$S timeout 520 bash $D build 2>&1 | grep -v "^$" | tail -n 12
  echo "staged after $(( $(date +%s) - t0 )) s"
  exit 0 ;;
warm)
  mkdir -p $S/warmparts && cp .stage/warm/*/*__pgsr_nomesh__[0-9]*of*.txz $S/warmparts/ && ls -la $S/warmparts
  exit 0 ;;
splitin)
  mkdir -p $S/splitparts && cp .stage/splitin/*/*__split__*of*.txz $S/splitparts/ && ls $S/splitparts | wc -l
  exit 0 ;;
launch)
  mkdir -p $S/exch
  for job in ${SCENES:?SCENES names the scenes}; do
    sc=${job%%:*}
    [ -f .stage/exch/$sc/meta.json ] || { echo "no .stage/exch/$sc carried"; exit 1; }
    rm -rf $S/exch/$sc && cp -r .stage/exch/$sc $S/exch/
  done
  for job in $SCENES; do
    # SCENE runs SYSTEMS; SCENE:SYS1,SYS2 its own systems (e.g. "bunny64:pgsr_nomesh chair:2dgs")
    sc=${job%%:*}; sys=${SYSTEMS:-}
    [ "$job" != "$sc" ] && { sys=${job#*:}; sys=${sys//,/ }; }
    [ -n "$sys" ] || { echo "$sc: no systems (SYSTEMS, or SCENE:SYSTEMS)"; exit 1; }
    for s in $sys pgsr_nomesh; do  # a run launched again is packed and sent again
      rm -f $P/$sc.$s.done $P/${sc}__${s}__*.txz $P/sent/${sc}__${s}__*.txz
    done
    pgsr_args=${PGSR_ARGS:-}
    if [ -n "${FROM_WARMUP:-}" ]; then
      if [[ " $sys " == *" pgsr_nomesh "* ]]; then
        echo "$sc: FROM_WARMUP starts pgsr's mesh stage from the carried warm-up; pgsr_nomesh would train it again"
        exit 1
      elif [[ " $sys " == *" pgsr "* ]]; then
        # the warm-up's parts, carried by the warm step, for the mesh stage (run_pgsr.py checks it is this scene's)
        unpack_parts ${sc}__pgsr_nomesh $S/warm/$sc $S/warmparts || exit 1
        pgsr_args="$pgsr_args --from-warmup $S/warm/$sc"
      fi
    fi
    if [ -n "${RESUME:-}" ]; then
      [ "$sys" = pgsr ] || [ "$sys" = pgsr_nomesh ] || {
        echo "$sc: RESUME goes on with one stopped run: pgsr's mesh stage or pgsr_nomesh's warm-up"; exit 1; }
      # the stopped run's folder, as its wait step sent it; device.sh launch keeps it for --resume
      unpack_parts ${sc}__${sys}__split $S/res/$sc/$sys $S/splitparts || exit 1
      pgsr_args="$pgsr_args --resume"
    fi
    PGSR_ARGS=$pgsr_args STAGE=$S bash $D launch "$S/exch/$sc" -- $sys
  done
  WAIT=${WAIT:-560} ;;
wait) ;;
*) echo "unknown step $step"; exit 2 ;;
esac
end=$(( t0 + ${WAIT:-540} ))
mkdir -p $OUT/sl
[ -n "${RESEND:-}" ] && rm -f $P/sent/*
runs=($S/res/*/*.log)
[ ${#runs[@]} -gt 0 ] || { echo "no runs under $S/res (a fresh machine? launch first)"; exit 3; }
jobs_left() { local n=0 l; for l in $S/res/*/*.log; do [ -f ${l%.log}.rc ] || n=$((n + 1)); done; echo $n; }
unpacked() {
  local n=0 l d
  for l in $S/res/*/*.log; do
    d=${l%.log}; [ -f $d.rc ] && [ ! -f $P/$(basename $(dirname $d)).${d##*/}.done ] && n=$((n + 1))
  done
  echo $n
}
unsent() { local n=0 f; for f in $P/*.txz; do [ -f $P/sent/${f##*/} ] || n=$((n + 1)); done; echo $n; }
pack_finished() {  # each finished run once: its result's files, xz in 10 MiB parts named SCENE__SYSTEM__IofN.txz
  local l d sys sc files f m i tmps name
  for l in $S/res/*/*.log; do
    d=${l%.log}; sys=${d##*/}; sc=$(basename $(dirname $d))
    [ -f $d.rc ] && [ ! -f $P/$sc.$sys.done ] || continue
    cp $l $d/device.log 2>/dev/null
    files=(); name=$sys
    for f in run.json renders.npz device.log log.txt; do [ -f $d/$f ] && files+=($f); done
    if [ $sys = pgsr_nomesh ] && [ -f $d/warmup/mesh/tsdf_fusion_post.ply ]; then files+=(warmup/mesh/tsdf_fusion_post.ply)
    elif [ -f $d/mesh.ply ]; then files+=(mesh.ply)
    elif [ -f $d/split.json ]; then  # a stage stopped at its checkpoint (--stop-at, --stop-after): --resume's
      files+=($(python3 -c "import json, sys; print(' '.join(json.load(open(sys.argv[1]))['carry']))" $d/split.json))
      name=${sys}__split  # parts of their own: never taken for a finished result's
    fi
    rm -f $P/tmp.*
    if ! tar -C $d -c "${files[@]}" | xz -T0 -6 | split -b 10M - $P/tmp.; then
      echo "$sc/$sys: packing failed"; continue
    fi
    tmps=($P/tmp.*); m=${#tmps[@]}; i=0
    for f in "${tmps[@]}"; do i=$((i + 1)); mv $f $(printf "$P/%s__%s__%02dof%02d.txz" $sc $name $i $m); done
    touch $P/$sc.$sys.done
    echo "$sc/$sys: rc $(cat $d.rc), ${files[*]} in $m parts"
  done
}
while [ "$(date +%s)" -lt $end ]; do
  pack_finished
  [ "$(jobs_left)" = 0 ] && [ "$(unpacked)" = 0 ] || [ "$(unsent)" -ge 6 ] && break
  sleep 10
done
pack_finished
n=0
for f in $P/*.txz; do
  [ ! -f $P/sent/${f##*/} ] && [ $n -lt 6 ] && cp $f $OUT/sl/ && touch $P/sent/${f##*/} && n=$((n + 1))
done
for l in $S/res/*/*.log; do
  d=${l%.log}; echo "$d rc=$(cat $d.rc 2>/dev/null || echo running): $(tail -n 1 $l | cut -c1-200)"
  # a running peer's progress bar (train.py's tqdm, in the run's log.txt): its iteration and rate
  [ -f $d.rc ] || [ ! -f $d/log.txt ] || tail -c 20000 $d/log.txt | tr '\r' '\n' | grep -a "progress" | tail -n 1 | cut -c1-160
done
ls $OUT/sl
if [ "$(jobs_left)" = 0 ] && [ "$(unpacked)" = 0 ] && [ "$(unsent)" = 0 ]; then echo "all results sent"
else echo "$(jobs_left) runs going, $(unsent) parts to send after $(( $(date +%s) - t0 )) s: call wait again"; fi
