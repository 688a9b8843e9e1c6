# Lease step "wgeo" (#59, design/decisions.md "Open: PGSR's multi-view geometric consistency"): wtopo's CUDA default
# beside the lab's geometric term (lab/geo_consistency.py, GEO=0.03) on DTU scan24 and the unbounded scenes, in three
# staging calls and no Open3D (nothing of the peers runs). Here, once: bash lab/device/stage.sh warp (.stage/w1-w3
# from .stage/p1-p3), and .stage/dtu_raw/dtu_scan24 (a copy of ../shared/data/dtu_scan24, 11 MB). Calls, carrying:
#   .stage/w1 .stage/smallpeers/whl           bash lab/device/wgeo.sh part
#   .stage/w2                                 bash lab/device/wgeo.sh part
#   .stage/w3 .stage/dtu_raw .stage/usd       SCENES="dtu_scan24 chair_env ..." bash lab/device/wgeo.sh launch
# (usd-core only for bunny_env, the bunny being a USD asset), then, within 30 s of each other,
#   TAG=b_ WAIT=... PAR=1 SCORE_TIMEOUT=150 bash lab/device/wait_fits.sh   until every scene is scored.
# launch installs Warp, the wheels and wtopo, exports the scenes (DTU from .stage/dtu_raw), then per scene two fits
# side by side: b_plain (the default) and b_geo; DTU's plain fit is b_fusion instead (its depths fused again per
# FUSION variant, default 1:4:5,2:4:2, for the pictures of lab/scene_fusion.py). Every fit shares the GPU.
# The term's product form (the branch geo-kernel: the Warp op and the plan entry, on for textured scenes) is measured
# from a checkout of that branch, whose plain chain then has the term: CHAINS="plain" beside a chain with
# --set losses.multiview_geometric=0 (add one to bias_all.sh there), not the lab patch's geo chain.
source lab/device/lease_env.sh
t0=$(date +%s)
case ${1:-} in
part)
  mkdir -p $S/whl $S/exch $S/res
  for d in .stage/w[0-9]*; do cp $d/big.part* $S/; done
  [ -d .stage/smallpeers/whl ] && cp .stage/smallpeers/whl/*.whl $S/whl/
  ls $S | tr '\n' ' '; echo
  ;;
launch)
  for d in .stage/w[0-9]*; do cp $d/big.part* $S/; done
  n=$(ls $S/big.part* 2>/dev/null | wc -l)
  [ "$n" = 3 ] || { echo "$n of the three big.part files staged: run the part step for each"; exit 1; }
  [ -d .stage/usd ] && python3 -m pip install -q --no-index --no-deps --no-compile --target $S/site .stage/usd/*.whl
  STAGE=$S bash $D install 2>&1 | tail -n 2  # its import check names Open3D missing: nothing here needs it
  python3 -c "import warp, wtopo; warp.init(); print('warp', warp.__version__, 'cuda', warp.is_cuda_available())" \
    || exit 1
  touch $S/t_installed
  SCENES=${SCENES:-dtu_scan24 chair_env mug_torus_env bunny_env}
  export NOUSD=1
  [[ " $SCENES " == *" dtu_scan24 "* ]] && { lease_dtu; tail -n 1 $S/exch_dtu.log; }
  others=$(echo " $SCENES " | sed 's/ dtu_scan24 / /')
  [ -n "${others// }" ] && { SCENES="$others" CHAINS=" " NOWAIT=1 bash lab/device/bias_all.sh || exit 1; }
  for sc in $SCENES; do
    if [ $sc = dtu_scan24 ]; then
      SCENES=$sc FUSION=${FUSION:-1:4:5,2:4:2} CHAINS="fusion geo" NOWAIT=1 bash lab/device/bias_all.sh
    else
      SCENES=$sc CHAINS="plain geo" NOWAIT=1 bash lab/device/bias_all.sh
    fi
  done
  ;;
*) echo "usage: bash lab/device/wgeo.sh part|launch"; exit 2 ;;
esac
echo "wgeo.sh ${1}: $(( $(date +%s) - t0 )) s"
