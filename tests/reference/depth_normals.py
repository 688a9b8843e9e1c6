# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference of :func:`wtopo.depth_normals.depth_normals` (the formulation the kernel replaced):
points along the rays, central differences on slices, the cross product, the masks as boolean algebra."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["depth_normals_torch"]


def depth_normals_torch(depth, origins, directions, valid, eps=1e-8):
    """``(normals [H, W, 3], mask [H, W])`` as the kernel documents them, in torch ops."""
    p = origins + directions * torch.where(valid, depth, torch.zeros_like(depth))[..., None]
    dx = p[1:-1, 2:] - p[1:-1, :-2]
    dy = p[2:, 1:-1] - p[:-2, 1:-1]
    n = torch.cross(dx, dy, dim=-1)
    inner = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
    length = n.norm(dim=-1, keepdim=True)
    inner = inner & (length[..., 0] > eps)
    n = n / length.clamp_min(eps)
    facing = (n * directions[1:-1, 1:-1]).sum(-1, keepdim=True)
    n = torch.where(facing > 0, -n, n)
    n = torch.where(inner[..., None], n, torch.zeros_like(n))
    out = F.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
    return out, F.pad(inner, (1, 1, 1, 1), value=False)
