# SPDX-License-Identifier: Apache-2.0
"""Does Warp's CUDA radix sort still sort after a Warp device allocation failed (as the final re-mesh's
does with many fits on one GPU), and does ``wtopo._bridge.recover_after_oom`` put it back in order?

    PYTHONPATH=/tmp/site:. python3 lab/device/warp_oom_sort.py     (on the device: lab/gpu.md)

Fills the GPU so that a 768^3 Poisson solve (the final re-mesh's) cannot allocate its field, re-solves on
the CPU as :func:`wtopo.fitting._final_mesh.poisson_remesh` does, then checks a million-pair sort twice; then the
same with the recovery in between. Measured with Warp 1.19.0 on an H200 (lab/gpu.md).
"""

import torch
import warp as wp

from wtopo import _bridge
from wtopo.fitting.proxy import poisson_mesh

DEV = "cuda:0"


def sort_ok(n: int = 1_000_000) -> bool:
    """Whether Warp's radix sort of ``n`` random int32 pairs on the GPU comes out sorted and paired."""
    k = torch.randint(0, 1 << 30, (2 * n,), dtype=torch.int32, device=DEV)
    v = torch.arange(2 * n, dtype=torch.int32, device=DEV)
    k0 = k[:n].clone()
    wp.utils.radix_sort_pairs(wp.from_torch(k), wp.from_torch(v), n)
    torch.cuda.synchronize()
    return bool(torch.equal(k[:n], torch.sort(k0).values)) and bool(torch.equal(k0[v[:n].long()], k[:n]))


def fail_poisson(p: torch.Tensor, n: torch.Tensor) -> None:
    """A 768^3 Poisson solve with 3 % of the GPU free: Warp's field allocation fails; then the CPU's."""
    hog = torch.empty(int(torch.cuda.mem_get_info()[0] * 0.97) // 4, dtype=torch.float32, device=DEV)
    try:
        poisson_mesh(p, n, torch.ones(len(p), device=DEV), 768, sigma=1.0, padding=0.1)
        print("the solve did not run out of memory")
    except RuntimeError as e:
        print("GPU solve:", str(e)[:80])
    del hog
    torch.cuda.empty_cache()
    _, f = poisson_mesh(p.cpu(), n.cpu(), torch.ones(len(p)), 64, sigma=1.0, padding=0.1)
    print("CPU solve:", f.shape[0], "faces")


def main() -> None:
    n = torch.nn.functional.normalize(torch.randn(20000, 3, device=DEV), dim=1)
    p = 0.5 + 0.4 * n
    print("sort before any failure:", sort_ok())
    fail_poisson(p, n)
    print("sorts after the failure:", sort_ok(), sort_ok())
    fail_poisson(p, n)
    _bridge.recover_after_oom(DEV)
    print("sorts after the failure and recover_after_oom:", sort_ok(), sort_ok())


if __name__ == "__main__":
    main()
