# SPDX-License-Identifier: Apache-2.0
"""NumPy reference of :func:`wtopo.vertex_support.view_agreement`: the support rules' projection as the mesh policy
computed it before the Warp kernel (:meth:`wtopo.Camera.project` in float64, the pixel a vertex falls in)."""

from __future__ import annotations

import numpy as np


def view_agreement_numpy(vertices, camera, depth, tolerance=None, relative=0.02) -> np.ndarray:
    """Boolean [V]: vertex ``i`` [V, 3] lies in front of ``camera``, inside its image, on a pixel of ``depth`` [H, W]
    (0: none) whose depth is positive and within ``tolerance`` (``None``: ``relative`` times the vertex's z-depth)
    of its z-depth."""
    uv, z = camera.project(np.asarray(vertices, np.float64))
    with np.errstate(invalid="ignore"):
        u, v = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
    out = np.zeros(len(z), bool)
    d = np.asarray(depth, np.float64)[v[ok].astype(np.int64), u[ok].astype(np.int64)]
    tol = relative * z[ok] if tolerance is None else tolerance
    out[ok] = (d > 0) & (np.abs(d - z[ok]) <= tol)
    return out
