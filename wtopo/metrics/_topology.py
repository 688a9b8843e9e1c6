# SPDX-License-Identifier: Apache-2.0
"""Mesh topology and what a reconstruction adds and misses: :func:`mesh_stats`, :func:`floaters`, :func:`holes`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.components import face_components
from ._surface import _DEFAULT_SAMPLES, _check_samples, _check_tau, _mesh_arrays, _n_faces, _Surface


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
    ncomp = face_components(f, len(v))[0]
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
    n_comp, label = face_components(pf, len(pv))
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
