# SPDX-License-Identifier: Apache-2.0
"""Differentiable operations: torch tensors in, torch tensors out, gradients through Warp.

Each function validates its arguments before any launch and documents dtype, shape, units and
which inputs it is differentiable with respect to.
"""

from __future__ import annotations

import importlib

_OPS = {
    "oriented_points": "wtopo.oriented_points",
    "scatter_trilinear": "wtopo.scatter",
    "sample_trilinear": "wtopo.scatter",
    "poisson_indicator": "wtopo.poisson",
    "marching_cubes": "wtopo.marching_cubes",
    "rasterize_surfels": "wtopo.rasterize",
    "RenderOutput": "wtopo.rasterize",
    "RasterConfig": "wtopo.rasterize",
    "raycast_mesh": "wtopo.raycast",
    "MeshRender": "wtopo.raycast",
    "closest_faces": "wtopo.raycast",
    "photometric_loss": "wtopo.photometric",
    "depth_normals": "wtopo.depth_normals",
}

__all__ = list(_OPS)


def __getattr__(name):
    if name in _OPS:
        return getattr(importlib.import_module(_OPS[name]), name)
    raise AttributeError(f"module 'wtopo.ops' has no attribute {name!r}")
