# Lease step "outline" (#59): the GPU rows of the CUDA default since the outline offset (a1ff951), each fit's mesh
# before the offset kept beside it (lab/pre_outline.py, bias_all.sh's default chain), on the nine object scenes of
# benchmarks/peers.md, bunny64 again at seed 1, and, with PROXY_TOO=1, the proxy at 320 nodes on the three ten-view
# scenes (the 64-view chair came 13-19 % closer with it in three pairs, rows_2026-12-07d-f). After the three
# staging calls of lab/device/alone.sh part, in one call: bash lab/device/o_all.sh (install, exports, launch; the
# fits run detached), then `TAG=b_ WAIT=... PAR=1 SCORE_TIMEOUT=200 bash lab/device/wait_fits.sh` calls until
# every scene is scored. Every fit shares the GPU and its 16 cores: times compare within the lease only.
# NOUSD=1 (exported): the fits write no timeline, so that the call that carries .stage/p3, .stage/gl and
# .stage/smallpeers/whl also installs and launches (two staging calls, p1 and p2, before it; the timeline's writing
# is a few seconds of a fit and no part of its mesh). The bunny's export still needs usd-core (the bunny is a USD
# asset): with bunny64 in ALL, a call carrying .stage/usd must install it first (rows_2026-12-07g:
# `source lab/device/lease_env.sh; python3 -m pip install -q --no-index --no-deps --target $S/site .stage/usd/*.whl`).
# The other scenes export without it (checked on the CPU with pxr hidden): the six object scenes not yet run with
# the outline offset take three calls, `bash lab/device/alone.sh part` carrying .stage/p1, then .stage/p2, then
# `export NOUSD=1 ALL="chair bowl mug torus blob_flat chair_sparse"; bash lab/device/o_all.sh; TAG=b_ WAIT=...
# PAR=1 SCORE_TIMEOUT=150 bash lab/device/wait_fits.sh` carrying .stage/p3 .stage/gl .stage/smallpeers/whl.
source lab/device/lease_env.sh
set -o pipefail
t0=$(date +%s)
[ -n "${NOUSD:-}" ] && bash lab/device/alone.sh part
bash lab/device/alone.sh install 2>&1 | tail -n 3 || { echo "install failed"; exit 1; }
ALL=${ALL:-bunny64 chair bowl mug torus blob_flat chair_sparse torus_sparse mug_sparse}
if [[ " $ALL " == *" bunny64 "* ]] && ! python3 -c "import pxr" 2>/dev/null; then
  echo "bunny64's export needs usd-core: carry .stage/usd and install it first (above)"; exit 1
fi
SCENES="$ALL" CHAINS=" " NOWAIT=1 bash lab/device/bias_all.sh || exit 1
for sc in $ALL; do SCENES=$sc CHAINS=default NOWAIT=1 bash lab/device/bias_all.sh; done
[[ " $ALL " == *" bunny64 "* ]] && SCENES=bunny64 CHAINS=seed1 NOWAIT=1 bash lab/device/bias_all.sh
if [ -n "${PROXY_TOO:-}" ]; then
  for sc in chair_sparse torus_sparse mug_sparse; do SCENES=$sc CHAINS=proxy NOWAIT=1 bash lab/device/bias_all.sh; done
fi
echo "o_all.sh: launched after $(( $(date +%s) - t0 )) s"
