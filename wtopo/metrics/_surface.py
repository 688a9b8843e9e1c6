# SPDX-License-Identifier: Apache-2.0
"""Mesh input and exact point-to-surface queries shared by the geometry metrics.

Meshes are read from a ``trimesh.Trimesh`` or a ``(verts, faces)`` pair (numpy or torch) into
float64 / int64 arrays, sampled uniformly by area, and queried for exact closest points: Warp's BVH
(:class:`wtopo.raycast.MeshRaycaster`, on the CPU) finds the closest face in float32 around the mesh's
centre and casts the rays; the distance to that face is recomputed in float64.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..raycast import MeshRaycaster

_DEFAULT_SAMPLES = 100_000


def _mesh_arrays(name: str, mesh) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        v, f = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v, f = mesh
    else:
        raise TypeError(f"{name} must be a trimesh.Trimesh or a (verts, faces) pair, got {type(mesh).__name__}")
    v = v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
    f = f.detach().cpu().numpy() if isinstance(f, torch.Tensor) else np.asarray(f)
    v = v.astype(np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name} vertices must have shape [V, 3], got {list(v.shape)}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name} faces must have shape [F, 3], got {list(f.shape)}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"{name} faces must index [0, {len(v) - 1}], got range [{f.min()}, {f.max()}]")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} vertices must be finite")
    return v, f


def _require_surface(name: str, v, f):
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if len(f) == 0 or area.sum() <= 0:
        raise ValueError(f"{name} must have faces of positive total area, got {len(f)} faces, area {area.sum():.3g}")
    return tri, area


def sample_surface(mesh, n_samples: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points uniformly distributed by area on a mesh.

    Returns:
        ``(points [n, 3] float64, face_index [n] int64)``; deterministic given ``seed``.
    """
    v, f = _mesh_arrays("mesh", mesh)
    tri, area = _require_surface("mesh", v, f)
    rng = np.random.default_rng(seed)
    fi = rng.choice(len(f), size=int(n_samples), p=area / area.sum())
    r1, r2 = rng.random(int(n_samples)), rng.random(int(n_samples))
    s = np.sqrt(r1)  # sqrt warps the unit square onto the triangle with uniform density
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", w, tri[fi]), fi


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points on triangles (a, b, c) to points p, all [M, 3] (Ericson, Real-Time Collision
    Detection, 5.1.5), vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + ab * v[:, None] + ac * w[:, None]  # interior
        # edge regions
        t_ab = np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out[m] = (a + ab * t_ab[:, None])[m]
        t_ac = np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out[m] = (a + ac * t_ac[:, None])[m]
        t_bc = np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0)
        m = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        out[m] = (b + (c - b) * t_bc[:, None])[m]
    # vertex regions last: they take precedence
    m = (d1 <= 0) & (d2 <= 0)
    out[m] = a[m]
    m = (d3 >= 0) & (d4 <= d3)
    out[m] = b[m]
    m = (d6 >= 0) & (d5 <= d6)
    out[m] = c[m]
    return out


class _Surface:
    """Area samples of a mesh plus a Warp BVH for exact point-to-surface queries: the BVH finds the
    closest face (and a ray's first hit) in float32 around the mesh's centre, the distance to that face is
    then recomputed in float64."""

    def __init__(self, name: str, mesh, n_samples: int, seed: int):
        self.v, self.f = _mesh_arrays(name, mesh)
        self.tri, _ = _require_surface(name, self.v, self.f)
        fn = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        self.face_normals = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        if n_samples:
            self.points, self.face_index = sample_surface((self.v, self.f), n_samples, seed=seed)
        used = self.v[np.unique(self.f)]
        self.center = 0.5 * (used.min(0) + used.max(0))
        self.bbox_diag = float(np.linalg.norm(used.max(0) - used.min(0)))
        self._bvh = MeshRaycaster()
        self._bvh_v = torch.as_tensor((self.v - self.center).astype(np.float32))
        self._bvh_f = torch.as_tensor(self.f.astype(np.int32))

    def closest_points(self, q: np.ndarray) -> np.ndarray:
        """Closest points [M, 3] float64 of this surface to query points [M, 3]."""
        fi = self.closest(q)[1]
        t = self.tri[fi]
        return _closest_on_triangles(q, t[:, 0], t[:, 1], t[:, 2])

    def cast(self, rays: np.ndarray) -> np.ndarray:
        """Distance [M] float64 along unit rays [M, 6] (origin relative to ``center``, direction) to
        the first hit of this surface (float32 precision), ``inf`` on a miss."""
        r32 = torch.as_tensor(np.ascontiguousarray(rays, dtype=np.float32))
        hit = self._bvh.raycast(self._bvh_v, self._bvh_f, rays=(r32[:, :3], r32[:, 3:]))
        return np.where(hit.mask.numpy(), hit.depth.numpy().astype(np.float64), np.inf)

    def closest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance [M] float64, face [M] int64) from query points [M, 3] to this surface."""
        q32 = np.ascontiguousarray(q - self.center, dtype=np.float32)
        fi = self._bvh.closest_faces(self._bvh_v, self._bvh_f, torch.as_tensor(q32))[0].numpy()
        fi = fi.astype(np.int64)
        t = self.tri[fi]
        d = np.linalg.norm(_closest_on_triangles(q, t[:, 0], t[:, 1], t[:, 2]) - q, axis=1)
        return d, fi


def _check_samples(n_samples) -> int:
    if isinstance(n_samples, bool) or int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    return int(n_samples)


def _n_faces(name: str, mesh) -> int:
    return len(_mesh_arrays(name, mesh)[1])


def _check_positive(value, name: str) -> float:
    t = float(value)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return t


def _check_tau(tau) -> float:
    return _check_positive(tau, "tau")
