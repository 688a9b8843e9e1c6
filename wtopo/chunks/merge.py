# SPDX-License-Identifier: Apache-2.0
"""Merge chunk results: each chunk keeps its core, meshes are welded across the cuts.

A chunk's mesh keeps the faces whose centroid lies in its core and its surfels those whose centre
does (:func:`~.partition.core_owner`: the cores partition space, so nothing is kept twice or
lost between two chunks). The pieces are concatenated and the vertices on their open boundaries
that lie near a cut are welded to the nearest boundary vertex of the neighbouring chunk within a
tolerance (``ChunkConfig.weld_fraction`` of the median boundary edge length), which closes the seam
where the two fits agree to within a fraction of an edge; elsewhere the seam stays open (counted in
the merge report).

Limitations:
    Welding snaps vertices, it does not re-triangulate: where two chunks' surfaces differ by more
    than the tolerance across a cut, a crack of that size stays.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .partition import ChunkPlan, core_owner

__all__ = ["keep_core_faces", "weld_boundaries", "merge_meshes", "merge_surfels", "boundary_edges_near"]


def keep_core_faces(mesh: trimesh.Trimesh, plan: ChunkPlan, index: int) -> trimesh.Trimesh:
    """The faces of ``mesh`` (world frame) whose centroid lies in chunk ``index``'s core."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    keep = core_owner(mesh.triangles_center, plan) == index
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out


def _open_edges(faces: np.ndarray) -> np.ndarray:
    """Edges [E, 2] (sorted vertex pairs) used by exactly one face."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    return uniq[count == 1]


def boundary_edges_near(mesh: trimesh.Trimesh, cuts, band: float) -> int:
    """Open edges of ``mesh`` whose midpoint lies within ``band`` of a cut plane ``(axis, coordinate)``:
    the seam's cracks (0 when the merge closed it)."""
    if len(mesh.faces) == 0 or not cuts:
        return 0
    e = _open_edges(np.asarray(mesh.faces))
    mid = 0.5 * (mesh.vertices[e[:, 0]] + mesh.vertices[e[:, 1]])
    near = np.zeros(len(e), bool)
    for a, c in cuts:
        near |= np.abs(mid[:, a] - c) <= band
    return int(near.sum())


def weld_boundaries(pieces: list[trimesh.Trimesh], cuts, tolerance: float | None, fraction: float
                    ) -> tuple[trimesh.Trimesh, dict]:
    """Concatenate ``pieces`` and weld open-boundary vertices of different pieces near the ``cuts``.

    Args:
        pieces: one mesh per chunk (world frame), already reduced to its core.
        cuts: interior cut planes ``(axis, coordinate)``.
        tolerance: weld distance, world units; ``None``: ``fraction`` of the median open-edge length.
        fraction: see ``tolerance``.

    Returns:
        ``(mesh, info)``: the merged mesh and the weld counts (tolerance, welded vertices, open
        edges near the cuts before and after).
    """
    pieces = [p for p in pieces if len(p.faces)]
    if not pieces:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False), {"welded": 0}
    verts, faces, owner, off = [], [], [], 0
    for k, p in enumerate(pieces):
        verts.append(np.asarray(p.vertices, np.float64))
        faces.append(np.asarray(p.faces, np.int64) + off)
        owner.append(np.full(len(p.vertices), k))
        off += len(p.vertices)
    v, f, own = np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)
    open_e = _open_edges(f)
    lengths = np.linalg.norm(v[open_e[:, 0]] - v[open_e[:, 1]], axis=1)
    tol = float(tolerance) if tolerance is not None else (fraction * float(np.median(lengths)) if len(lengths) else 0.0)
    bverts = np.unique(open_e)
    near = np.zeros(len(bverts), bool)
    for a, c in cuts:
        near |= np.abs(v[bverts, a] - c) <= 2.0 * tol
    cand = bverts[near]
    before = boundary_edges_near(trimesh.Trimesh(v, f, process=False), cuts, 2.0 * tol) if tol > 0 else 0
    parent = np.arange(len(v))
    welded = 0
    if len(cand) > 1 and tol > 0:
        from scipy.spatial import cKDTree

        pairs = cKDTree(v[cand]).query_pairs(tol, output_type="ndarray")
        pairs = pairs[own[cand[pairs[:, 0]]] != own[cand[pairs[:, 1]]]]  # only across chunks
        d = np.linalg.norm(v[cand[pairs[:, 0]]] - v[cand[pairs[:, 1]]], axis=1)
        used = np.zeros(len(v), bool)
        for i in np.argsort(d):  # closest pairs first; each vertex welds once (a matching, no chains)
            a, b = cand[pairs[i, 0]], cand[pairs[i, 1]]
            if used[a] or used[b]:
                continue
            used[a] = used[b] = True
            mid = 0.5 * (v[a] + v[b])
            v[a] = mid
            parent[b] = a
            welded += 1
    f = parent[f]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    f = f[good]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.remove_unreferenced_vertices()
    after = boundary_edges_near(mesh, cuts, 2.0 * tol) if tol > 0 else 0
    return mesh, {"tolerance": tol, "welded": welded, "open_edges_near_cuts_before": before,
                  "open_edges_near_cuts_after": after}


def merge_meshes(meshes: dict, plan: ChunkPlan, *, tolerance: float | None = None, fraction: float = 0.75
                 ) -> tuple[trimesh.Trimesh, dict]:
    """Keep each chunk's core faces and weld the pieces (see the module docstring).

    Args:
        meshes: ``{chunk index: trimesh.Trimesh}`` in the world frame.
        plan: the :class:`~.partition.ChunkPlan` they were fitted under.
        tolerance: weld distance in world units, or ``None`` (``fraction`` of the median open-edge length).
        fraction: see ``tolerance``.

    Returns:
        ``(mesh, info)``.
    """
    pieces = [keep_core_faces(m, plan, i) for i, m in sorted(meshes.items())]
    mesh, info = weld_boundaries(pieces, plan.cuts(), tolerance, fraction)
    info["faces_per_chunk"] = {int(i): int(len(p.faces)) for i, p in zip(sorted(meshes), pieces)}
    return mesh, info


def merge_surfels(surfels: dict, plan: ChunkPlan):
    """Concatenate each chunk's surfels whose centre lies in its core.

    Args:
        surfels: ``{chunk index: wtopo.io.SurfelArrays}`` in the world frame (``read_surfels_ply``).
        plan: the chunk plan.

    Returns:
        ``(means, quats, scales, opacities, sh)`` float32 arrays, SH padded to the highest degree.
    """
    keep = []
    for i, s in sorted(surfels.items()):
        sel = core_owner(s.means, plan) == i
        keep.append((s, sel))
    k = max((s.sh.shape[1] for s, _ in keep), default=1)
    cat = lambda get: np.concatenate([get(s)[sel] for s, sel in keep]) if keep else np.zeros((0,))  # noqa: E731
    sh = np.concatenate([np.pad(s.sh[sel], ((0, 0), (0, k - s.sh.shape[1]), (0, 0))) for s, sel in keep]) \
        if keep else np.zeros((0, 1, 3), np.float32)
    return (cat(lambda s: s.means), cat(lambda s: s.quats), cat(lambda s: s.scales), cat(lambda s: s.opacities), sh)
