# SPDX-License-Identifier: Apache-2.0
"""Chamfer on the observed part of a reference: the surface the training views actually saw.

DTU's protocol scores a reconstruction only where its structured-light scan observed the object
(an observation mask); a synthetic truth has no such mask, and a sparse capture leaves part of it
unseen (the inside of a cup from ten views). Whatever a method puts there is a guess that no
photograph can check. :func:`observed_chamfer` keeps the truth's area samples seen by at least
``min_views`` cameras (a ray from the camera's centre reaches the sample before any other part of
the truth, and the sample projects inside the image), and the reconstruction's samples whose nearest
truth sample is one of those.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ._distance import ChamferResult, _chamfer_result
from ._surface import _DEFAULT_SAMPLES, _check_positive, _check_samples, _Surface


@dataclass
class ObservedChamfer:
    """Chamfer restricted to the observed part of the reference (:func:`observed_chamfer`).

    Attributes:
        result: the Chamfer figures over the kept samples (:class:`ChamferResult`; relative fields
            normalised by the whole reference's bounding-box diagonal).
        observed: fraction of the reference's area seen by at least ``min_views`` cameras.
        scored: fraction of the reconstruction's area whose nearest reference sample is observed.
        views: how many cameras saw each reference sample, int64 [n_samples].
    """

    result: ChamferResult
    observed: float
    scored: float
    views: np.ndarray


def view_counts(points: np.ndarray, mesh, cameras, *, tolerance: float) -> np.ndarray:
    """How many of ``cameras`` see each of ``points`` on ``mesh`` (int64 [N]).

    A point is seen by a camera when it lies in front of it, projects inside its image, and the ray
    from the camera's centre towards it first meets ``mesh`` no nearer than ``tolerance`` (world
    units) before the point (Warp's BVH ray cast, on the CPU).

    Args:
        points: world points [N, 3] on (or within ``tolerance`` of) ``mesh``.
        mesh: the occluding surface (``trimesh.Trimesh`` or ``(verts, faces)``).
        cameras: a sequence of :class:`wtopo.Camera`.
        tolerance: > 0, world units.
    """
    tol = _check_positive(tolerance, "tolerance")
    return _view_counts(np.asarray(points, dtype=np.float64), _Surface("mesh", mesh, 0, 0), cameras, tol)


def _view_counts(p: np.ndarray, s: _Surface, cameras, tolerance: float) -> np.ndarray:
    """:func:`view_counts` against a built surface ``s`` (its BVH reused), ``tolerance`` checked."""
    count = np.zeros(len(p), dtype=np.int64)
    for cam in cameras:
        uv, z = cam.project(p)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        if not inside.any():
            continue
        c = np.asarray(cam.center, dtype=np.float64)
        d = p[inside] - c
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(c - s.center, d.shape), d / dist[:, None]], axis=1)
        t = s.cast(rays)  # distance to the first hit, inf on a miss (it grazes past the point)
        count[np.flatnonzero(inside)[t >= dist - tolerance]] += 1
    return count


def observed_chamfer(a, b, cameras, *, min_views: int = 2, tolerance: float | None = None,
                     n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> ObservedChamfer:
    """Chamfer between reconstruction ``a`` and reference ``b`` on the part of ``b`` the cameras saw.

    Sampling and distances as in :func:`wtopo.metrics.chamfer` (same seeds, so the reference's
    samples are the same ones). Completeness averages over the reference samples seen by at least
    ``min_views`` of ``cameras`` (:func:`view_counts`); accuracy over the reconstruction's samples
    whose nearest reference sample is one of those (so a guess over an unseen region is not scored,
    and a floater is scored against the observed surface nearest to it).

    Args:
        a: reconstruction mesh.
        b: reference mesh, in the cameras' frame.
        cameras: the training cameras (:class:`wtopo.Camera`), not held-out ones.
        min_views: >= 1; two views fix a point by triangulation.
        tolerance: occlusion slack in world units; default 0.1 % of ``b``'s bounding-box diagonal.
        n_samples: samples per surface.
        seed: sampling seed.

    Raises:
        ValueError: ``min_views`` < 1, no cameras, or no reference sample observed.
    """
    if isinstance(min_views, bool) or int(min_views) != min_views or min_views < 1:
        raise ValueError(f"min_views must be an integer >= 1, got {min_views!r}")
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras must hold at least one camera, got none")
    n = _check_samples(n_samples)
    tol = None if tolerance is None else _check_positive(tolerance, "tolerance")
    sa, sb = _Surface("a", a, n, seed), _Surface("b", b, n, seed + 1)
    tol = 1e-3 * sb.bbox_diag if tol is None else tol
    views = _view_counts(sb.points, sb, cameras, tol)
    obs = views >= int(min_views)
    if not obs.any():
        raise ValueError(f"no sample of the reference is seen by {min_views} of the {len(cameras)} cameras")
    near = cKDTree(sb.points).query(sa.points, workers=-1)[1]
    keep = obs[near]
    acc = float(sb.closest(sa.points[keep])[0].mean()) if keep.any() else 0.0
    comp = float(sa.closest(sb.points[obs])[0].mean())
    return ObservedChamfer(_chamfer_result(acc, comp, sb.bbox_diag), float(obs.mean()), float(keep.mean()), views)
