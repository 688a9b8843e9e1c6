# Lease step "alone" (#59): wtopo's time from images to mesh with nothing else on the GPU, on the scenes where a
# peer's row ran alone (2DGS's bowl and 64-view mug, rows_2026-12-06ah: 301 and 256 s on an H100). wtopo's rows of
# those scenes shared the GPU with other fits. Here (once): bash lab/device/stage.sh big usd (about 4 minutes:
# .stage/p1-p3, the xz tar of the Warp and Open3D wheels in 47 MB parts, and .stage/usd), with .stage/gl,
# .stage/smallpeers and .stage/exch/{bowl,mug} from stage.sh's gl, smallpeers and sl_exch steps. One call each,
# carrying (each under 64 MiB with the 12.2 MiB tree; 54 MB parts, as before, no longer fit beside it):
#   .stage/p1                                          bash lab/device/alone.sh part
#   .stage/p2                                          bash lab/device/alone.sh part
#   .stage/p3 .stage/gl .stage/smallpeers/whl          bash lab/device/alone.sh part
#   .stage/usd                                         bash lab/device/alone.sh install
# then one scene a call, so that each fit has the GPU to itself (a fit takes a few minutes; its result comes back
# in 10 MiB parts, so call sl.sh wait again until it says "all results sent"):
#   .stage/exch/bowl    SCENES=bowl:wtopo WAIT=540 bash lab/device/sl.sh launch
#   .stage/exch/mug     SCENES=mug:wtopo WAIT=540 bash lab/device/sl.sh launch
# The steps may follow sl.sh stage and run beside a peer's run (Open3D is then left as that stage installed it); for
# a time alone, launch each fit only once the peers have stopped and their results are packed.
# and here: bash lab/device/sl.sh unpack /work/.device/N/sl ...; then score.py as for the peers (sl.sh says how).
source lab/device/lease_env.sh
t0=$(date +%s)
case ${1:-} in
part)  # whatever this call carries of the Warp and Open3D parts, the libGL debs and the small wheels
  mkdir -p $S/whl $S/gl
  for d in .stage/p[0-9]*; do cp $d/big.part* $S/; done
  [ -d .stage/gl ] && cp .stage/gl/*.deb $S/gl/
  [ -d .stage/smallpeers/whl ] && cp .stage/smallpeers/whl/*.whl $S/whl/
  ls $S | tr '\n' ' '; echo
  ;;
install)  # usd-core, then device.sh install: Warp and Open3D from the parts, the wheels, the libGL debs, wtopo
  n=$(ls $S/big.part* 2>/dev/null | wc -l)
  [ "$n" = 3 ] || { echo "$n of the three big.part files staged: run the part step for each"; exit 1; }
  if [ -d $S/site/open3d ] && [ ! -d $S/site/warp ]; then
    # sl.sh stage ran first (a peer may be running from it): take only Warp from the parts, so that device.sh
    # install never rewrites the Open3D a running peer has loaded
    cat $S/big.part* | xz -d -T0 | tar -x -C $S/site --wildcards 'warp/*' 'warp_lang-*' || exit 1
  fi
  lease_install || exit 1
  python3 -c "import warp, wtopo; warp.init(); print('warp', warp.__version__, 'cuda', warp.is_cuda_available())"
  ;;
*) echo "usage: bash lab/device/alone.sh part|install"; exit 2 ;;
esac
echo "alone.sh ${1}: $(( $(date +%s) - t0 )) s"
