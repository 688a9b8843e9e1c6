# SPDX-License-Identifier: Apache-2.0
"""Scene metrics: F-score inside a region of interest and how close a mesh comes to the cameras."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._surface import _DEFAULT_SAMPLES, _check_samples, _mesh_arrays, _n_faces, _Surface, sample_surface

_ROI_MAX_DRAW_FACTOR = 64  # in-box sampling gives up after drawing this many times n_samples points
#                            (a surface with almost no area in the box is reported with what it has)


def _check_box(lower, upper) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(-1) for b in (lower, upper))
    if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"lower and upper must be finite 3-vectors, got {lower!r} and {upper!r}")
    if np.any(hi <= lo):
        raise ValueError(f"upper must exceed lower on every axis, got lower={lo.tolist()}, upper={hi.tolist()}")
    return lo, hi


def _inside(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((p >= lo) & (p <= hi), axis=1)


def _sample_in_box(v: np.ndarray, f: np.ndarray, lo, hi, n: int, seed: int) -> np.ndarray:
    """Up to ``n`` points [<=n, 3] uniform by area on the part of the surface inside the box.

    Rejection sampling on the faces whose bounding box meets the box (uniform on that superset,
    so uniform on its intersection with the box), drawing more until ``n`` land inside.
    """
    if len(f) == 0:
        return np.zeros((0, 3))
    tri = v[f]
    meets = np.all((tri.min(axis=1) <= hi) & (tri.max(axis=1) >= lo), axis=1)
    tri = tri[meets]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if len(tri) == 0 or area.sum() <= 0:
        return np.zeros((0, 3))
    flat = (tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3))
    kept, drawn, k = [], 0, 0
    while sum(len(x) for x in kept) < n and drawn < _ROI_MAX_DRAW_FACTOR * n:
        have = sum(len(x) for x in kept)
        frac = have / drawn if drawn else 1.0
        m = min(int((n - have) / max(frac, 1.0 / _ROI_MAX_DRAW_FACTOR) * 1.1) + 16, _ROI_MAX_DRAW_FACTOR * n - drawn)
        p, _ = sample_surface(flat, m, seed=seed + 7919 * k)
        kept.append(p[_inside(p, lo, hi)])
        drawn, k = drawn + m, k + 1
    return np.concatenate(kept)[:n]


@dataclass
class ROIFScore:
    """Precision, recall and F-score inside a region of interest (Tanks and Temples protocol).

    Attributes:
        precision: fraction of the prediction's in-box surface within ``tau`` of the ground truth
            (0 when the prediction has no surface in the box).
        recall: fraction of the ground truth's in-box surface within ``tau`` of the prediction.
        f_score: harmonic mean of the two (0 when both are 0).
        tau: the threshold, in the meshes' units.
        accuracy: mean distance of the prediction's in-box samples to the ground truth (``inf``
            when there are none).
        completeness: mean distance of the ground truth's in-box samples to the prediction
            (``inf`` when the prediction is empty).
        n_pred: prediction samples inside the box.
        n_gt: ground-truth samples inside the box.
    """

    precision: float
    recall: float
    f_score: float
    tau: float
    accuracy: float
    completeness: float
    n_pred: int
    n_gt: int


def roi_f_score(pred_mesh, gt_mesh, lower, upper, tau: float, *, n_samples: int = _DEFAULT_SAMPLES,
                seed: int = 0) -> ROIFScore:
    """F-score of a reconstruction against the ground truth inside the box ``[lower, upper]``.

    The Tanks-and-Temples evaluation restricted to a region of interest: both surfaces are
    sampled uniformly by area and only the samples inside the box are scored. Distances are exact
    point-to-surface distances to the *whole* other mesh, so a predicted point just inside the box
    whose true surface continues just outside it is not punished, nor is a ground-truth point
    matched by predicted surface just outside the box.

    Args:
        pred_mesh: reconstruction (``trimesh.Trimesh`` or ``(verts, faces)``); may be empty.
        gt_mesh: ground truth, all geometry (it may extend far beyond the box); it must have
            surface inside the box.
        lower: box lower corner [3], the meshes' units.
        upper: box upper corner [3].
        tau: distance threshold (e.g. 0.5 % of the box diagonal), the meshes' units.
        n_samples: samples inside the box per surface.
        seed: sampling seed (deterministic given it).

    Raises:
        ValueError: bad box, ``tau`` or ``n_samples``; ``gt_mesh`` has no surface in the box.
    """
    t = float(tau)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"tau must be finite and > 0, got {tau!r}")
    n = _check_samples(n_samples)
    lo, hi = _check_box(lower, upper)
    gt = _Surface("gt_mesh", gt_mesh, 0, seed)
    gt_pts = _sample_in_box(gt.v, gt.f, lo, hi, n, seed + 1)
    if len(gt_pts) == 0:
        raise ValueError(f"gt_mesh has no surface inside the box lower={lo.tolist()}, upper={hi.tolist()}")
    pv, pf = _mesh_arrays("pred_mesh", pred_mesh)
    pred_pts = _sample_in_box(pv, pf, lo, hi, n, seed)
    if len(pred_pts) == 0:
        return ROIFScore(0.0, 0.0, 0.0, t, math.inf, math.inf, 0, len(gt_pts))
    pred = _Surface("pred_mesh", (pv, pf), 0, seed)
    d_pred = gt.closest(pred_pts)[0]
    d_gt = pred.closest(gt_pts)[0]
    p, r = float((d_pred <= t).mean()), float((d_gt <= t).mean())
    f = 0.0 if p + r == 0 else 2 * p * r / (p + r)
    return ROIFScore(p, r, f, t, float(d_pred.mean()), float(d_gt.mean()), len(pred_pts), len(gt_pts))


def camera_clearance(mesh, camera_centers) -> np.ndarray:
    """Distance from each camera centre to the nearest point of a mesh surface.

    Exact point-to-triangle distances (closest face found by Warp's BVH, distance recomputed in
    float64), not distances to vertices, so a large face passing next to a camera counts.

    Args:
        mesh: ``trimesh.Trimesh`` or ``(verts, faces)``; may be empty.
        camera_centers: [N, 3] camera centres, the mesh's units (e.g. ``scene.camera_centers``).

    Returns:
        float64 [N], the mesh's units (``inf`` for every camera when the mesh has no faces).
    """
    c = np.asarray(camera_centers, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or not np.all(np.isfinite(c)):
        raise ValueError(f"camera_centers must be finite with shape [N, 3], got shape {list(c.shape)}")
    if _n_faces("mesh", mesh) == 0 or len(c) == 0:
        return np.full(len(c), math.inf)
    return _Surface("mesh", mesh, 0, 0).closest(c)[0]
