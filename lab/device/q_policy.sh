# Lease step q (after the p1, p2 and p3 + gl + small/whl staging calls; carry .stage/usd): the final mesh's host
# steps on the H200's host after the policy's own face selection (bench_mesh_policy.py --device cuda), in the little
# device time a session has left.
source lab/device/lease_env.sh
t0=$(date +%s)
lease_install || exit 1
echo "installed after $(( $(date +%s) - t0 )) s"
mkdir -p $OUT/q
timeout ${LIMIT:-100} python3 benchmarks/bench_mesh_policy.py --device cuda > $OUT/q/mesh_policy_gpu.txt 2>&1
tail -n 10 $OUT/q/mesh_policy_gpu.txt
