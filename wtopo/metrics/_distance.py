# SPDX-License-Identifier: Apache-2.0
"""Surface distances between a reconstruction and a reference mesh: Chamfer, F-score, normal consistency.

Both surfaces are sampled uniformly by area and each sample's exact distance to the other surface
is taken (:class:`~wtopo.metrics._surface._Surface`), so the result does not carry the sampling
density's bias of a plain point-to-point Chamfer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from ._surface import _DEFAULT_SAMPLES, _check_samples, _check_tau, _Surface


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
    acc = float(cKDTree(vb).query(va, workers=-1)[0].mean())
    comp = float(cKDTree(va).query(vb, workers=-1)[0].mean())
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
    t = _check_tau(tau)
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


@dataclass
class InwardOffset:
    """Signed offset of a reconstruction ``a`` from a closed reference ``b`` along ``b``'s normals.

    Attributes:
        mean: mean signed distance of ``a``'s area samples to ``b``, positive inside ``b`` (a shrunk
            reconstruction), in the meshes' units; each sample's sign is its side of the plane of
            the closest face of ``b`` (``b`` wound outwards).
        median: the median of the same.
        inside: fraction of ``a``'s area inside ``b`` (signed distance > 0).
    """

    mean: float
    median: float
    inside: float


def inward_offset(a, b, *, n_samples: int = _DEFAULT_SAMPLES, seed: int = 0) -> InwardOffset:
    """How far reconstruction ``a`` lies inside reference ``b`` on average (:class:`InwardOffset`):
    a systematic shrink shows as a positive mean with most of the area inside, noise as a mean near 0.
    Sampling as in :func:`chamfer`."""
    n = _check_samples(n_samples)
    sa, sb = _Surface("a", a, n, seed), _Surface("b", b, n, seed + 1)
    _, fd = sb.closest(sa.points)
    fd = np.asarray(fd, dtype=np.int64)
    s = -np.einsum("ij,ij->i", sa.points - sb.v[sb.f[fd, 0]], sb.face_normals[fd])
    return InwardOffset(float(s.mean()), float(np.median(s)), float((s > 0).mean()))
