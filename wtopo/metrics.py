# SPDX-License-Identifier: Apache-2.0
"""Error measures for reconstructed meshes and rendered images.

Geometry (host, float64, SciPy ``cKDTree``): :func:`chamfer`, :func:`chamfer_vertices`,
:func:`f_score` (and its two halves with their components and areas: :func:`floaters`, reconstructed
surface far from the truth, and :func:`holes`, true surface far from the reconstruction),
:func:`normal_consistency`, :func:`mesh_stats`, and for scenes
:func:`roi_f_score` (Tanks-and-Temples F-score inside a region of interest) and
:func:`camera_clearance` (how close a mesh comes to the cameras); for recovered camera poses
:func:`align_similarity` (least-squares similarity between two point sets, Umeyama). Surfaces are
sampled uniformly by area; distances are exact point-to-triangle distances to the other surface (closest face from
Open3D's Embree scene, distance recomputed in float64), so the result does not carry the sampling
density's bias of a plain point-to-point Chamfer.

Images (torch, differentiable): :func:`psnr`, :func:`ssim`.

Meshes may be given as a ``trimesh.Trimesh`` or a ``(verts [V, 3], faces [F, 3])`` pair of numpy
arrays or torch tensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from .photometric import gaussian_window as _gaussian_window

__all__ = [
    "ChamferResult",
    "FScore",
    "Floaters",
    "Holes",
    "chamfer",
    "chamfer_vertices",
    "f_score",
    "floaters",
    "holes",
    "normal_consistency",
    "psnr",
    "ssim",
    "mesh_stats",
    "sample_surface",
    "ROIFScore",
    "roi_f_score",
    "camera_clearance",
    "SimilarityAlignment",
    "align_similarity",
    "refine_alignment",
]

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
    """Area samples of a mesh plus an Open3D (Embree) closest-point scene for exact
    point-to-surface queries: Embree finds the closest face in float32 around the mesh's centre,
    the distance to that face is then recomputed in float64."""

    def __init__(self, name: str, mesh, n_samples: int, seed: int):
        import open3d as o3d

        self.v, self.f = _mesh_arrays(name, mesh)
        self.tri, _ = _require_surface(name, self.v, self.f)
        fn = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        self.face_normals = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        if n_samples:
            self.points, self.face_index = sample_surface((self.v, self.f), n_samples, seed=seed)
        used = self.v[np.unique(self.f)]
        self.center = 0.5 * (used.min(0) + used.max(0))
        self.bbox_diag = float(np.linalg.norm(used.max(0) - used.min(0)))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor((self.v - self.center).astype(np.float32)),
                                  o3d.core.Tensor(self.f.astype(np.uint32)))

    def closest_points(self, q: np.ndarray) -> np.ndarray:
        """Closest points [M, 3] float64 of this surface to query points [M, 3]."""
        fi = self.closest(q)[1]
        t = self.tri[fi]
        return _closest_on_triangles(q, t[:, 0], t[:, 1], t[:, 2])

    def closest(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance [M] float64, face [M] int64) from query points [M, 3] to this surface."""
        import open3d as o3d

        r = self._scene.compute_closest_points(o3d.core.Tensor((q - self.center).astype(np.float32)))
        fi = r["primitive_ids"].numpy().astype(np.int64)
        t = self.tri[fi]
        d = np.linalg.norm(_closest_on_triangles(q, t[:, 0], t[:, 1], t[:, 2]) - q, axis=1)
        return d, fi


@dataclass
class ChamferResult:
    """Symmetric surface distance between a reconstruction ``a`` and a reference ``b``.

    Attributes:
        chamfer: ``(accuracy + completeness) / 2``, in the meshes' units.
        accuracy: mean distance from ``a`` to ``b``.
        completeness: mean distance from ``b`` to ``a``.
        chamfer_rel: ``chamfer`` as a fraction of ``b``'s bounding-box diagonal.
        accuracy_rel: ``accuracy`` as that fraction.
        completeness_rel: ``completeness`` as that fraction.
        diagonal: ``b``'s bounding-box diagonal.
    """

    chamfer: float
    accuracy: float
    completeness: float
    chamfer_rel: float
    accuracy_rel: float
    completeness_rel: float
    diagonal: float



def _chamfer_result(acc: float, comp: float, diag: float) -> ChamferResult:
    ch = 0.5 * (acc + comp)
    return ChamferResult(ch, acc, comp, ch / diag, acc / diag, comp / diag, diag)


def _check_samples(n_samples) -> int:
    if isinstance(n_samples, bool) or int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    return int(n_samples)


def chamfer(a, b, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> ChamferResult:
    """Chamfer distance between the surfaces of ``a`` (reconstruction) and ``b`` (reference).

    Both surfaces are sampled uniformly by area (``n_samples`` points each, deterministic given
    ``seed``); each sample's exact distance to the other surface is averaged in both directions.

    Args:
        a: reconstruction mesh (``trimesh.Trimesh`` or ``(verts, faces)``).
        b: reference mesh; its bounding-box diagonal normalises the ``*_rel`` fields.
        n_samples: samples per surface.
        seed: sampling seed.
    """
    n = _check_samples(n_samples)
    sa, sb = _Surface("a", a, n, seed), _Surface("b", b, n, seed + 1)
    acc = float(sb.closest(sa.points)[0].mean())
    comp = float(sa.closest(sb.points)[0].mean())
    return _chamfer_result(acc, comp, sb.bbox_diag)


def chamfer_vertices(a, b) -> ChamferResult:
    """Vertex-to-vertex Chamfer distance (nearest vertex in the other mesh, both directions).

    Cheap and independent of sampling, but biased by the vertex density; prefer :func:`chamfer`.
    Accepts meshes or point clouds ``[V, 3]``.
    """
    def verts(name, m):
        if hasattr(m, "vertices"):
            m = m.vertices
        elif isinstance(m, (tuple, list)) and len(m) == 2:
            m = m[0]
        v = m.detach().cpu().numpy() if isinstance(m, torch.Tensor) else np.asarray(m)
        v = v.astype(np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"{name} vertices must have shape [V>0, 3], got {list(v.shape)}")
        return v

    va, vb = verts("a", a), verts("b", b)
    acc = float(cKDTree(vb).query(va)[0].mean())
    comp = float(cKDTree(va).query(vb)[0].mean())
    return _chamfer_result(acc, comp, float(np.linalg.norm(vb.max(0) - vb.min(0))))


@dataclass
class FScore:
    """Precision, recall and F-score at distance ``tau``.

    Attributes:
        precision: fraction of ``a``'s surface within ``tau`` of ``b``.
        recall: fraction of ``b``'s surface within ``tau`` of ``a``.
        f_score: harmonic mean of the two (0 when both are 0).
        tau: the threshold, in the meshes' units.
    """

    precision: float
    recall: float
    f_score: float
    tau: float


def f_score(a, b, tau: float, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> FScore:
    """F-score of reconstruction ``a`` against reference ``b`` at distance ``tau`` (same units as
    the meshes; e.g. ``0.005 * diagonal``). Sampling as in :func:`chamfer`."""
    t = float(tau)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"tau must be finite and > 0, got {tau!r}")
    n = _check_samples(n_samples)
    sa, sb = _Surface("a", a, n, seed), _Surface("b", b, n, seed + 1)
    p = float((sb.closest(sa.points)[0] <= t).mean())
    r = float((sa.closest(sb.points)[0] <= t).mean())
    f = 0.0 if p + r == 0 else 2 * p * r / (p + r)
    return FScore(p, r, f, t)


def normal_consistency(a, b, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0, oriented: bool = False) -> float:
    """Mean ``|n_a . n_b|`` between each sample's face normal and the normal of the closest face on
    the other surface, averaged over both directions (1 = identical orientation field). With
    ``oriented=True`` the signed cosine is averaged instead (flipped faces count as -1)."""
    n = _check_samples(n_samples)
    sa, sb = _Surface("a", a, n, seed), _Surface("b", b, n, seed + 1)
    vals = []
    for src, dst in ((sa, sb), (sb, sa)):
        _, fd = dst.closest(src.points)
        c = np.einsum("ij,ij->i", src.face_normals[src.face_index], dst.face_normals[fd])
        vals.append((c if oriented else np.abs(c)).mean())
    return float(0.5 * (vals[0] + vals[1]))


# -- scenes: region of interest and cameras ------------------------------------------------------
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


def _n_faces(name: str, mesh) -> int:
    return len(_mesh_arrays(name, mesh)[1])


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

    Exact point-to-triangle distances (closest face found by Embree, distance recomputed in
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


@dataclass(frozen=True)
class SimilarityAlignment:
    """The least-squares similarity ``target ~ scale * rotation @ source + translation`` found by
    :func:`align_similarity`, and how far each point stays from its target after it."""

    scale: float
    """Scale factor, > 0."""
    rotation: np.ndarray
    """Proper rotation [3, 3], float64 (determinant +1)."""
    translation: np.ndarray
    """Translation [3], float64, the target's units."""
    residuals: np.ndarray
    """Distance of each mapped source point from its target [N], float64, the target's units."""

    @property
    def rms(self) -> float:
        """Root mean square of :attr:`residuals` (the target's units)."""
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    def apply(self, points) -> np.ndarray:
        """Map points [..., 3] of the source frame into the target frame (float64)."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * p @ self.rotation.T + self.translation

    def apply_to_camera(self, camera):
        """A :class:`wtopo.Camera` of the source frame as the same camera in the target frame: it sees
        :meth:`apply` of every point where ``camera`` saw the point (intrinsics and distortion kept)."""
        from .camera import Camera

        w2c = camera.world_to_camera
        out = np.eye(4)
        out[:3, :3] = w2c[:3, :3] @ self.rotation.T
        out[:3, 3] = self.scale * w2c[:3, 3] - out[:3, :3] @ self.translation  # camera coordinates scaled by s
        return Camera(camera.K, out, camera.width, camera.height, camera.distortion, camera.name)

    def apply_to_mesh(self, mesh):
        """A ``trimesh.Trimesh`` of the source frame (or ``(verts, faces)``) mapped into the target frame."""
        import trimesh

        v, f = _mesh_arrays("mesh", mesh)
        return trimesh.Trimesh(self.apply(v), f, process=False)


def align_similarity(source, target) -> SimilarityAlignment:
    """The similarity (scale, rotation, translation) that best maps ``source`` onto ``target`` in
    the least-squares sense, in closed form (Umeyama 1991): e.g. camera centres recovered by
    structure from motion, which live in a frame of their own, onto the true centres.

    Args:
        source: points [N, 3] (N >= 3, not all on one line), any units.
        target: corresponding points [N, 3].

    Returns:
        :class:`SimilarityAlignment` with the residual of every point.

    Raises:
        ValueError: shapes differ or are not [N >= 3, 3], non-finite values, or ``source`` is
            degenerate (all points coincide or lie on a line: the rotation is undetermined).

    References:
        S. Umeyama, "Least-squares estimation of transformation parameters between two point
        patterns", IEEE TPAMI 13(4), 1991.
    """
    x = np.asarray(source, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape or len(x) < 3:
        raise ValueError(f"source and target must both have shape [N >= 3, 3], got {list(x.shape)} and "
                         f"{list(y.shape)}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("source and target must be finite")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    var_x = float((xc ** 2).sum(1).mean())
    u, d, vt = np.linalg.svd(yc.T @ xc / len(x))
    # the source must span at least a plane; relative to its spread, a second singular value this
    # small means colinear points (float64 round-off sits near 1e-16)
    sx = np.linalg.svd(xc / max(math.sqrt(var_x), np.finfo(np.float64).tiny), compute_uv=False)  # [N, N] U otherwise
    if var_x == 0 or sx[1] < 1e-9 * sx[0]:
        raise ValueError("source points must not all coincide or lie on one line: the rotation is undetermined")
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection would fit better: take the best rotation
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float((d * sign).sum() / var_x)
    trans = my - scale * rot @ mx
    res = np.linalg.norm(scale * x @ rot.T + trans - y, axis=1)
    return SimilarityAlignment(scale, rot, trans, res)


_REFINE_START = 0.02  # first correspondence cut-off, fraction of the target's diagonal: a camera
# alignment leaves ~0.1-0.5 % (benchmarks/sfm.md), so 2 % keeps every true pair and drops far floaters
_REFINE_STOP = 0.005  # last cut-off (F-score's 0.5 %): pairs farther than this do not steer the end
_REFINE_SHRINK = 0.8  # cut-off factor per iteration: 2 % -> 0.5 % in 7 iterations


def refine_alignment(source, target, *, initial: SimilarityAlignment | None = None, iterations: int = 25,
                     n_samples: int = 20_000, seed: int = 0) -> SimilarityAlignment:
    """Refine a similarity between two surfaces by symmetric, trimmed ICP (Tanks and Temples' last step).

    The Tanks and Temples protocol (Knapitsch et al. 2017) aligns a reconstruction made from
    estimated cameras to the ground truth by the camera centres, then refines that similarity by
    ICP against the ground-truth surface, because the camera alignment carries the structure from
    motion's own error (on the synthetic capture of ``benchmarks/sfm.md`` the centres' similarity is
    0.4 % off in scale, a focal-length / distance trade the centres cannot see). Here each
    iteration pairs area samples of the mapped source with their closest points on the target
    *and* samples of the target with their closest points on the mapped source (so a surface that
    covers only part of the other is not dragged into it), drops pairs farther apart than a
    cut-off shrinking from 2 % to 0.5 % of the target's diagonal, and solves the pairs' similarity
    in closed form (:func:`align_similarity`).

    Args:
        source: ``trimesh.Trimesh`` or ``(verts, faces)`` to move (e.g. a fitted mesh already in the
            target's frame by the camera alignment).
        target: ``trimesh.Trimesh`` or ``(verts, faces)`` (e.g. the ground truth).
        initial: similarity to start from (the identity when ``None``).
        iterations: ICP iterations (>= 1).
        n_samples: area samples drawn on each surface.
        seed: sampling seed.

    Returns:
        :class:`SimilarityAlignment` from ``source`` to ``target`` (``initial`` included), with the
        distances of the source samples to the target after it as ``residuals``.

    Raises:
        ValueError: an empty surface, ``iterations`` < 1, no pair within the first cut-off.

    Limitations:
        Seven degrees of freedom fitted against the truth also absorb a reconstruction's own
        global scale or shift error: report the camera-only figure beside the refined one.

    References:
        A. Knapitsch, J. Park, Q.-Y. Zhou and V. Koltun, "Tanks and Temples: Benchmarking
        Large-Scale Scene Reconstruction", ACM TOG 36(4), 2017.
    """
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    n = _check_samples(n_samples)
    src = _Surface("source", source, n, seed)
    tgt = _Surface("target", target, n, seed + 1)
    if initial is None:
        s, rot, t = 1.0, np.eye(3), np.zeros(3)
    else:
        s, rot, t = initial.scale, np.asarray(initial.rotation, np.float64), np.asarray(initial.translation, np.float64)
    for it in range(iterations):
        cut = tgt.bbox_diag * max(_REFINE_STOP, _REFINE_START * _REFINE_SHRINK ** it)
        p = s * src.points @ rot.T + t  # source samples, mapped
        q = tgt.closest_points(p)
        keep = np.linalg.norm(q - p, axis=1) < cut
        back = (tgt.points - t) @ rot / s  # target samples in the source frame
        r = src.closest_points(back)
        keep_back = s * np.linalg.norm(r - back, axis=1) < cut
        if not keep.any() and not keep_back.any():
            raise ValueError(f"no point of source lies within {cut:.4g} (2 % of the target's diagonal) of target: "
                             "align them first (initial=)")
        x = np.concatenate([src.points[keep], r[keep_back]])
        y = np.concatenate([q[keep], tgt.points[keep_back]])
        if len(x) < 3:
            break
        a = align_similarity(x, y)
        s, rot, t = a.scale, a.rotation, a.translation
    mapped = s * src.points @ rot.T + t
    return SimilarityAlignment(float(s), rot, t, tgt.closest(mapped)[0])


# -- images -------------------------------------------------------------------------------------
def _image_pair(pred, target):
    for nm, x in (("pred", pred), ("target", target)):
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{nm} must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim not in (3, 4) or x.shape[-1] != 3:
            raise ValueError(f"{nm} must have shape [H, W, 3] or [N, H, W, 3], got {list(x.shape)}")
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {list(pred.shape)} and {list(target.shape)}")
    if pred.ndim == 3:
        pred, target = pred[None], target[None]
    return pred, target.to(pred.dtype)


def psnr(pred: torch.Tensor, target: torch.Tensor, *, mask: torch.Tensor | None = None,
         max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB, averaged over images.

    Args:
        pred: rendered colours, [H, W, 3] or [N, H, W, 3], float, differentiable.
        target: reference colours, same shape.
        mask: optional pixels to score, [H, W] or [N, H, W], bool.
        max_val: peak value (1 for images in [0, 1]).

    Returns:
        Scalar tensor (``inf`` for identical images).
    """
    pred, target = _image_pair(pred, target)
    se = (pred - target) ** 2
    if mask is None:
        mse = se.mean(dim=(1, 2, 3))
    else:
        m = mask if mask.ndim == 3 else mask[None]
        if tuple(m.shape) != tuple(pred.shape[:3]):
            raise ValueError(f"mask must have shape {list(pred.shape[:3])}, got {list(mask.shape)}")
        m = m.to(pred.dtype)[..., None]
        mse = (se * m).sum(dim=(1, 2, 3)) / (3 * m.sum(dim=(1, 2, 3))).clamp_min(1)
    return (10 * torch.log10(max_val ** 2 / mse)).mean()


def ssim(pred: torch.Tensor, target: torch.Tensor, *, window: int = 11, sigma: float = 1.5,
         k1: float = 0.01, k2: float = 0.03, data_range: float = 1.0) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, averaged over pixels,
    channels and images.

    Statistics are population (not sample) moments over the ``valid`` window positions, matching
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)``.

    Args:
        pred: [H, W, 3] or [N, H, W, 3], float, differentiable; H and W >= ``window``.
        target: same shape.
        window: side of the Gaussian window [pixels], odd.
        sigma: standard deviation of the window [pixels].
        k1: luminance stabiliser, times ``data_range``.
        k2: contrast stabiliser, times ``data_range``.
        data_range: value range of the images (1 for [0, 1]).

    References:
        Wang, Bovik, Sheikh, Simoncelli, "Image quality assessment: from error visibility to
        structural similarity", IEEE TIP 2004.
    """
    pred, target = _image_pair(pred, target)
    if pred.shape[1] < window or pred.shape[2] < window:
        raise ValueError(f"images must be at least {window}x{window}, got {pred.shape[2]}x{pred.shape[1]}")
    g = _gaussian_window(window, sigma, pred.dtype, pred.device)
    x, y = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    # one separable blur of all five moments at once (5 x 3 channels, grouped)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    c = stack.shape[1]
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, window)
    wy = g.view(1, 1, -1, 1).expand(c, 1, window, 1)
    blurred = torch.nn.functional.conv2d(torch.nn.functional.conv2d(stack, wx, groups=c), wy, groups=c)
    mx, my, exx, eyy, exy = blurred.chunk(5, dim=1)
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


# -- topology -------------------------------------------------------------------------------------
def mesh_stats(mesh) -> dict:
    """Counts and topology of a triangle mesh.

    Returns:
        dict with ``n_vertices`` (referenced by faces), ``n_faces``, ``n_edges``,
        ``boundary_edges`` (used by one face), ``nonmanifold_edges`` (used by three or more),
        ``watertight`` (every edge used by exactly two faces), ``winding_consistent`` (every
        directed edge used once), ``n_components`` (face-connected through shared vertices),
        ``euler`` (V - E + F), ``genus`` (for a watertight single component, else ``None``),
        ``area`` and ``volume`` (signed, ``None`` unless watertight).
    """
    v, f = _mesh_arrays("mesh", mesh)
    used = np.unique(f)
    nv, nf = int(len(used)), int(len(f))
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    ne = int(len(counts))
    boundary = int((counts == 1).sum())
    nonmanifold = int((counts > 2).sum())
    _, dcounts = np.unique(directed, axis=0, return_counts=True) if nf else (None, np.zeros(0))
    watertight = nf > 0 and boundary == 0 and nonmanifold == 0
    winding = bool(watertight and (dcounts == 1).all())
    ncomp = _face_components(f, len(v))[0]
    euler = nv - ne + nf
    tri = v[f]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = float(0.5 * np.linalg.norm(cr, axis=1).sum())
    volume = float(np.einsum("ij,ij->i", tri[:, 0], cr).sum() / 6.0) if watertight else None
    genus = (2 - euler) // 2 if watertight and ncomp == 1 else None
    return {
        "n_vertices": nv, "n_faces": nf, "n_edges": ne,
        "boundary_edges": boundary, "nonmanifold_edges": nonmanifold,
        "watertight": bool(watertight), "winding_consistent": winding,
        "n_components": ncomp, "euler": int(euler), "genus": genus,
        "area": area, "volume": volume,
    }


# -- what a reconstruction adds and misses: floaters and holes -------------------------------------
def _face_components(f: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Connected components of faces that share a vertex: ``(count, label [F])``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = len(f)
    if nf == 0:
        return 0, np.zeros(0, np.int64)
    rows = np.repeat(np.arange(nf), 3)
    adj = coo_matrix((np.ones(3 * nf), (rows, f.reshape(-1))), shape=(nf, n_vertices)).tocsr()
    n, label = connected_components(adj @ adj.T, directed=False)
    return int(n), label.astype(np.int64)


def _check_tau(tau) -> float:
    t = float(tau)
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"tau must be finite and > 0, got {tau!r}")
    return t


@dataclass
class Floaters:
    """Reconstructed surface that the ground truth does not explain.

    Attributes:
        area_fraction: fraction of the reconstruction's area farther than ``tau`` from the ground
            truth (``1 - precision`` of :func:`f_score` with the same samples).
        area: that area, in the meshes' units squared.
        count: connected components of the reconstruction with no point within ``tau`` of the
            ground truth (detached floaters).
        count_area: total area of those components.
        components: connected components of the reconstruction (faces sharing a vertex).
        tau: the threshold, in the meshes' units.
    """

    area_fraction: float
    area: float
    count: int
    count_area: float
    components: int
    tau: float


def floaters(pred, gt, tau: float, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> Floaters:
    """Floaters of reconstruction ``pred`` against the reference ``gt`` at distance ``tau``.

    ``pred`` is sampled uniformly by area (as in :func:`f_score`: the same ``seed`` gives the same
    samples, so ``area_fraction == 1 - precision``); each sample's exact distance to ``gt``
    decides whether it is far. A component is a floater when none of its area samples and none of
    its vertices lies within ``tau`` of ``gt``: the vertices make the count independent of the
    sampling for small components (a component smaller than the sample spacing still has its
    corners tested), while a component whose only contact with ``tau`` is inside a face and between
    samples may be counted as a floater.

    Args:
        pred: reconstruction (``trimesh.Trimesh`` or ``(verts, faces)``); an empty mesh has no floaters.
        gt: reference mesh.
        tau: distance threshold, the meshes' units (e.g. ``0.005 * diagonal``).
        n_samples: area samples on ``pred``.
        seed: sampling seed.
    """
    t = _check_tau(tau)
    n = _check_samples(n_samples)
    pv, pf = _mesh_arrays("pred", pred)
    if len(pf) == 0:
        return Floaters(0.0, 0.0, 0, 0.0, 0, t)
    sp = _Surface("pred", (pv, pf), n, seed)
    sg = _Surface("gt", gt, 0, seed + 1)
    area = 0.5 * np.linalg.norm(np.cross(sp.tri[:, 1] - sp.tri[:, 0], sp.tri[:, 2] - sp.tri[:, 0]), axis=1)
    d = sg.closest(sp.points)[0]
    far = float((d > t).mean())
    n_comp, label = _face_components(pf, len(pv))
    near = np.zeros(n_comp, bool)
    near[np.unique(label[sp.face_index[d <= t]])] = True
    vlabel = np.full(len(pv), -1, np.int64)
    vlabel[pf.reshape(-1)] = np.repeat(label, 3)
    used = np.nonzero(vlabel >= 0)[0]
    dv = sg.closest(pv[used])[0]
    near[np.unique(vlabel[used[dv <= t]])] = True
    comp_area = np.bincount(label, weights=area, minlength=n_comp)
    total = float(area.sum())
    return Floaters(far, far * total, int((~near).sum()), float(comp_area[~near].sum()), n_comp, t)


@dataclass
class Holes:
    """Reference surface that the reconstruction misses.

    Attributes:
        area_fraction: fraction of the reference's area farther than ``tau`` from the
            reconstruction (``1 - recall`` of :func:`f_score` with the same samples); 1 for an
            empty reconstruction.
        area: that area, in the meshes' units squared.
        tau: the threshold, in the meshes' units.
    """

    area_fraction: float
    area: float
    tau: float


def holes(pred, gt, tau: float, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> Holes:
    """Holes of reconstruction ``pred``: the area of the reference ``gt`` farther than ``tau`` from it.

    ``gt`` is sampled uniformly by area (the samples of :func:`f_score` with the same ``seed``, so
    ``area_fraction == 1 - recall``); each sample's exact distance to ``pred`` decides.

    Args:
        pred: reconstruction (``trimesh.Trimesh`` or ``(verts, faces)``); may be empty.
        gt: reference mesh.
        tau: distance threshold, the meshes' units.
        n_samples: area samples on ``gt``.
        seed: sampling seed.
    """
    t = _check_tau(tau)
    n = _check_samples(n_samples)
    sg = _Surface("gt", gt, n, seed + 1)
    total = float(0.5 * np.linalg.norm(np.cross(sg.tri[:, 1] - sg.tri[:, 0], sg.tri[:, 2] - sg.tri[:, 0]),
                                       axis=1).sum())
    if _n_faces("pred", pred) == 0:
        return Holes(1.0, total, t)
    d = _Surface("pred", pred, 0, seed).closest(sg.points)[0]
    frac = float((d > t).mean())
    return Holes(frac, frac * total, t)
