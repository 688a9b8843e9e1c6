# SPDX-License-Identifier: Apache-2.0
"""Pure-torch references for trilinear scatter / sample (node (i,j,k) at (i,j,k)/R, zero extension).

``scatter_trilinear_ref`` is also the ``index_add_`` peer of ``benchmarks/bench_scatter_poisson.py``.
"""

import torch


def trilinear_corners(points: torch.Tensor, resolution: int):
    """Flat node index [N, 8] (``-1`` where a node index reaches ``R``) and weights [N, 8]."""
    u = points * resolution
    base = torch.floor(u)
    f = u - base
    base = base.long()
    idx, wts = [], []
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                ijk = base + torch.tensor([di, dj, dk], device=points.device)
                w = ((f[:, 0] if di else 1 - f[:, 0]) * (f[:, 1] if dj else 1 - f[:, 1])
                     * (f[:, 2] if dk else 1 - f[:, 2]))
                valid = (ijk < resolution).all(dim=1)
                flat = (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2]
                idx.append(torch.where(valid, flat, torch.full_like(flat, -1)))
                wts.append(torch.where(valid, w, torch.zeros_like(w)))
    return torch.stack(idx, 1), torch.stack(wts, 1)


def scatter_trilinear_ref(points: torch.Tensor, values: torch.Tensor, resolution: int) -> torch.Tensor:
    """Scatter ``values [N, C]`` at ``points [N, 3]`` into ``[R, R, R, C]`` with ``index_add_``."""
    idx, w = trilinear_corners(points, resolution)
    c = values.shape[1]
    keep = idx >= 0
    contrib = (w.unsqueeze(-1) * values.unsqueeze(1))[keep]
    grid = torch.zeros(resolution ** 3, c, dtype=values.dtype, device=values.device)
    grid = grid.index_add(0, idx[keep], contrib)
    return grid.view(resolution, resolution, resolution, c)


def sample_trilinear_ref(grid: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of ``grid [R, R, R, C]`` at ``points [N, 3]`` (missing nodes read 0)."""
    r, c = grid.shape[0], grid.shape[3]
    idx, w = trilinear_corners(points, r)
    flat = grid.reshape(r ** 3, c)
    vals = flat[idx.clamp_min(0)] * (idx >= 0).unsqueeze(-1)
    return (w.unsqueeze(-1) * vals).sum(1)
