# SPDX-License-Identifier: Apache-2.0
"""USD plumbing shared by the timeline writer, the camera conversion and the readers."""

from __future__ import annotations

import re

import numpy as np

from ._common import as_array

__all__ = ["HAS_SPLAT_SCHEMA", "TimelineVerificationError"]

try:
    from pxr import UsdVol as _UsdVol

    HAS_SPLAT_SCHEMA = hasattr(_UsdVol, "ParticleField3DGaussianSplat")
except ImportError:  # usd-core without UsdVol
    _UsdVol = None
    HAS_SPLAT_SCHEMA = False
"""True when the installed usd-core has ``UsdVol.ParticleField3DGaussianSplat`` (OpenUSD >= 26.03)."""


class TimelineVerificationError(RuntimeError):
    """The written USD file, reopened, does not hold what was authored; the target is untouched."""


def _pxr():
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    return Gf, Sdf, Usd, UsdGeom, Vt


def _identifier(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return s if s and not s[0].isdigit() else "_" + s


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; +z for isolated vertices) [V, 3] float32."""
    v = verts.astype(np.float64)
    n = np.zeros_like(v)
    if faces.size:
        fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # length = 2 * area
        for k in range(3):
            for c in range(3):
                n[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=len(v))
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.where(ln > 0, ln, 1), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def _extent(points: np.ndarray, pad: float = 0.0) -> np.ndarray:
    if len(points) == 0:
        return np.zeros((2, 3), np.float32)
    return np.stack([points.min(0) - pad, points.max(0) + pad]).astype(np.float32)


def _mesh_arrays(verts, faces, prefix: str) -> tuple[np.ndarray, np.ndarray]:
    verts = as_array(f"{prefix}verts", verts, shape=(None, 3))
    faces = as_array(f"{prefix}faces", faces, shape=(None, 3), dtype=np.int32)
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"{prefix}faces must index [0, {len(verts)}), got range [{faces.min()}, {faces.max()}]")
    return verts, faces


def _all_times(attrs) -> list[float]:
    times = set()
    for a in attrs:
        times.update(a.GetTimeSamples())
    return sorted(times)
