# SPDX-License-Identifier: Apache-2.0
"""Shared test shapes: a sphere tiled by surfels, a textured plane with its true depth and normal."""

from __future__ import annotations

import numpy as np
import torch
import trimesh


def sphere_lattice(n: int, radius: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``n`` points of a Fibonacci lattice on the unit sphere: ``(unit normals [n, 3] float64, the same
    as points on a sphere of ``radius`` around the origin, sigma)``, where ``sigma`` is one lattice
    spacing on that sphere (discs of that standard deviation overlap their neighbours: no holes)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    nrm = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    return nrm, radius * nrm, float(radius * np.sqrt(4 * np.pi / n))


def textured_plane():
    """The quad ``z = 0``, ``[-1, 1]^2``, textured, seen by 8 hemisphere views of 96 x 72 px (black background)."""
    from wtopo import scenes

    quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    return scenes.from_mesh(quad, n_views=8, resolution=(96, 72), rig="hemisphere", texture="astronaut",
                            background="black", seed=1)


def plane_truth(cam, device="cpu") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Of :func:`textured_plane` seen by ``cam``: z-depth [H, W] along the camera's pixel rays, the up normal
    [H, W, 3] and alpha [H, W], all zero where the ray misses the quad (kept 0.05 inside its edges)."""
    o, d = cam.pixel_rays()
    t = -o[..., 2] / d[..., 2]
    hit = o + d * t[..., None]
    on = (t > 0) & (hit[..., 0].abs() < 0.95) & (hit[..., 1].abs() < 0.95)
    depth = torch.where(on, t, torch.zeros_like(t)).float()
    normal = torch.zeros(*depth.shape, 3)
    normal[..., 2] = 1.0
    return depth.to(device), (normal * on[..., None]).to(device), on.float().to(device)
