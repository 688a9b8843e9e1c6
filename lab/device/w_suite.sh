# Lease step w (#59's scene list): the hard suite's objects not yet in benchmarks/peers.md, gsplat at its published
# 30,000 iterations beside wtopo's CUDA default and wtopo without its loop, on the same exports. After the p1, p2 and
# p3 + gl + small/whl staging calls, in one call:
#   SCENES="torus mug_sparse" bash lab/device/w_suite.sh
# then, within 30 s of each other, calls of `TAG=w SYSTEMS="gsplat wtopo wtopo_noloop" bash lab/device/w_wait.sh`
# until it has scored every scene into $OUT/w/rows_SCENE.json. gsplat takes 10-16 minutes at 64 views of 512 px
# beside other jobs: two or three scenes a lease (the default: the dense torus and the ten-view mug). SYSTEMS picks the
# systems (default "gsplat wtopo wtopo_noloop"). Every scene of the suite has run beside gsplat: torus, bowl, blob_flat
# and torus_sparse as SCENES="torus bowl blob_flat torus_sparse" SYSTEMS="gsplat wtopo" (rows_2026-12-06w), the dense
# mug through lab/device/aa_all.sh (rows_2026-12-06aa).
source lab/device/lease_env.sh
t0=$(date +%s)
SCENES=${SCENES:-torus mug_sparse}
lease_install || exit 1
lease_prepare $SCENES
for sc in $SCENES; do
  STAGE=$S bash $D launch "$S/exch/$sc" -- ${SYSTEMS:-gsplat wtopo wtopo_noloop}
done
echo "launched after $(( $(date +%s) - t0 )) s"
TAG=w SYSTEMS="${SYSTEMS:-gsplat wtopo wtopo_noloop}" WAIT=$(( 560 - ($(date +%s) - t0) )) bash lab/device/w_wait.sh
