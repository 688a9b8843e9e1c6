# Lease step ad (#59): the official 2DGS at its published 30,000 iterations on SCENES (default "chair torus_sparse
# bunny64"), all at once, now that run_2dgs.py gives a masked capture's masks as its images' alpha (719bec1), which
# its TSDF reads (rows_2026-12-06ac ran without them). After the p1 and p2 staging calls, carrying .stage/p3
# .stage/gl .stage/small, in one call:
#   SCENES="chair torus_sparse bunny64" bash lab/device/ad_2dgs.sh
# then, within 30 s of each other, `RENDERS=1 TAG=ad SYSTEMS=2dgs bash lab/device/w_wait.sh` until every scene is
# scored into $OUT/ad/rows_SCENE.json (with each run's log's end in logs.txt).
source lab/device/lease_env.sh
t0=$(date +%s)
SCENES=${SCENES:-chair torus_sparse bunny64}
mkdir -p $S/whl $S/gl $S/peers
# every staged wheel but gsplat's (its JIT build would take the cores 2DGS's CUDA builds need)
cp .stage/p3/* $S/ && cp .stage/gl/* $S/gl/ && ls .stage/small/whl/*.whl | grep -v /gsplat- | xargs -I{} cp {} $S/whl/
cp -r .stage/small/peers/2dgs $S/peers/
lease_install || exit 1
lease_prepare $SCENES
for m in diff_surfel_rasterization simple_knn._C; do python3 -c "import $m" 2>&1 | tail -n 1 | sed "s/^/import $m: /"; done
for sc in $SCENES; do STAGE=$S bash $D launch "$S/exch/$sc" -- 2dgs; done
echo "launched after $(( $(date +%s) - t0 )) s"
RENDERS=1 TAG=ad SYSTEMS=2dgs WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/w_wait.sh
