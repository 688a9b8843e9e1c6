# SPDX-License-Identifier: Apache-2.0
"""Reference pieces for marching-cubes tests: a plain torch edge-vertex extractor, skimage's mesh
in wtopo's frame, analytic fields and mesh checks (closedness, orientation, area).

The torch extractor computes every crossed grid edge's vertex directly (one vectorised
expression per axis, differentiable through torch autograd), independent of the Warp kernels'
column walk, welding and tables.  Faces come from ``skimage.measure.marching_cubes`` (Lewiner).
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import torch


def spacing_of(shape, lower, upper) -> np.ndarray:
    """Distance between neighbouring nodes per axis."""
    return (np.asarray(upper, float) - np.asarray(lower, float)) / (np.asarray(shape, float) - 1)


def edge_vertices(field: torch.Tensor, level: float = 0.0, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0)):
    """Vertices of all crossed grid edges, ``[V, 3]``, differentiable w.r.t. ``field`` (torch autograd).

    Inside is ``field < level``.  Assumes no node equals ``level`` exactly (tie-free fields).
    """
    sp = torch.as_tensor(spacing_of(field.shape, lower, upper), dtype=field.dtype)
    lo = torch.as_tensor(np.asarray(lower, float), dtype=field.dtype)
    out = []
    for axis in range(3):
        a = field.narrow(axis, 0, field.shape[axis] - 1)
        b = field.narrow(axis, 1, field.shape[axis] - 1)
        crossed = (a < level) != (b < level)
        idx = torch.nonzero(crossed)
        av, bv = a[crossed], b[crossed]
        t = (level - av) / (bv - av)
        pos = idx.to(field.dtype)
        pos[:, axis] = pos[:, axis] + t
        out.append(lo + pos * sp)
    return torch.cat(out)


def skimage_mesh(field: np.ndarray, level: float = 0.0, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0)):
    """``skimage.measure.marching_cubes`` (Lewiner) mapped into the frame of ``lower``/``upper``."""
    from skimage.measure import marching_cubes

    sp = spacing_of(field.shape, lower, upper)
    verts, faces, _, _ = marching_cubes(np.asarray(field, np.float64), level, spacing=tuple(sp))
    return verts + np.asarray(lower, float), faces


def sphere_sdf(n: int, radius, *, lower=(-0.5, -0.5, -0.5), upper=(0.5, 0.5, 0.5), center=(0.0, 0.0, 0.0),
               dtype=torch.float64, shape=None) -> torch.Tensor:
    """Signed distance to a sphere (negative inside) sampled on the grid; ``radius`` may be a tensor."""
    shape = shape or (n, n, n)
    axes = [torch.linspace(lo, hi, s, dtype=dtype) - c for lo, hi, s, c in zip(lower, upper, shape, center)]
    gx, gy, gz = torch.meshgrid(*axes, indexing="ij")
    return (gx * gx + gy * gy + gz * gz).sqrt() - radius


def smooth_random_field(shape, seed: int, *, sigma: float = 2.5, dtype=torch.float64) -> torch.Tensor:
    """Gaussian-filtered white noise, zero mean and unit std: a smooth field with many surfaces."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    f = gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
    f = (f - f.mean()) / f.std()
    return torch.as_tensor(f, dtype=dtype)


def mesh_area(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Total triangle area (differentiable w.r.t. ``verts``)."""
    f = faces.long()
    a, b, c = verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]]
    return 0.5 * torch.linalg.cross(b - a, c - a).norm(dim=1).sum()


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed mesh; positive when its normals point outwards."""
    v = np.asarray(verts, np.float64)[np.asarray(faces, np.int64)]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def edge_report(faces: np.ndarray) -> dict:
    """Undirected edge use counts and directed edge repeats of a triangle list.

    A closed, consistently wound mesh uses every undirected edge exactly twice and every directed
    edge exactly once (its two faces traverse it in opposite directions).
    """
    f = np.asarray(faces, np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = Counter(map(tuple, np.sort(directed, axis=1).tolist()))
    dirc = Counter(map(tuple, directed.tolist()))
    return {
        "undirected_counts": Counter(und.values()),
        "boundary_edges": [e for e, n in und.items() if n == 1],
        "max_directed_repeat": max(dirc.values()) if dirc else 0,
        # edges not traversed equally often in both directions: holes or inconsistent winding
        "unbalanced_edges": [e for e in und if dirc.get(e, 0) != dirc.get(e[::-1], 0)],
    }


def match_points(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of ``a`` the index of, and distance to, the nearest row of ``b``."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(np.asarray(b, np.float64)).query(np.asarray(a, np.float64))
    return idx, dist


def ambiguous_cells(field: np.ndarray, level: float = 0.0) -> int:
    """Cells with a face whose diagonal corners share a side the other diagonal does not.

    On those faces (and in cells with an interior ambiguity, which need such faces) marching
    cubes variants may legitimately differ: skimage's Lewiner tiling resolves them with the
    asymptotic decider and may add an interior vertex, the classic table does not.
    """
    s = np.asarray(field) < level
    amb = np.zeros(tuple(n - 1 for n in s.shape), dtype=bool)
    for axis in range(3):
        a, b = [d for d in range(3) if d != axis]
        sl = [slice(None)] * 3

        def take(da, db, sl=sl, a=a, b=b):
            idx = list(sl)
            idx[a] = slice(da, s.shape[a] - 1 + da)
            idx[b] = slice(db, s.shape[b] - 1 + db)
            return s[tuple(idx)]

        face = (take(0, 0) == take(1, 1)) & (take(1, 0) == take(0, 1)) & (take(0, 0) != take(1, 0))
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        amb |= face[tuple(lo)] | face[tuple(hi)]
    return int(amb.sum())
