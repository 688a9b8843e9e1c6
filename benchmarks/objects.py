# SPDX-License-Identifier: Apache-2.0
"""Test objects the benchmarks share: truth meshes built from signed distance functions and trimesh
primitives with fixed shapes (a torus, a mug, a chair, a bowl, a bumpy blob), the meshing helper with an
optional on-disk cache, and an exact box clip. The hard suite (``lab/hard_scenes.py``) and the peers
benchmark (``benchmarks/peers/scenes.py``) render their scenes from these."""

from __future__ import annotations

import math
import os

import numpy as np
import trimesh

MESH_CACHE: list[str] = []  # a folder keeping the signed-distance meshes (a machine without scikit-image reads it)


# -- meshes from signed distance functions (negative inside) --------------------------------------
def _box(p, center, half):
    q = np.abs(p - np.asarray(center)) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _cylinder_z(p, center, radius, half_height):
    c = np.asarray(center)
    d = np.stack([np.linalg.norm(p[..., :2] - c[:2], axis=-1) - radius, np.abs(p[..., 2] - c[2]) - half_height], -1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)


def _torus_y(p, center, major, minor):
    """Torus whose axis is the y axis (it stands in the x-z plane)."""
    q = p - np.asarray(center)
    ring = np.linalg.norm(q[..., [0, 2]], axis=-1) - major
    return np.hypot(ring, q[..., 1]) - minor


def _sphere(p, center, radius):
    return np.linalg.norm(p - np.asarray(center), axis=-1) - radius


def sdf_mesh(sdf, lower, upper, spacing: float) -> trimesh.Trimesh:
    """The zero level of ``sdf`` (points [..., 3] -> values) on a grid over ``[lower, upper]``,
    outward-wound; surfaces that reach the grid's border stay open there."""
    import hashlib

    key = hashlib.sha1(repr((sdf.__qualname__, np.round(np.asarray(lower, np.float64), 9).tolist(),
                             np.round(np.asarray(upper, np.float64), 9).tolist(), spacing)).encode()).hexdigest()[:16]
    path = os.path.join(MESH_CACHE[0], f"{key}.npz") if MESH_CACHE else None
    if path and os.path.exists(path):  # a machine without scikit-image reads what another one built
        with np.load(path) as z:
            return trimesh.Trimesh(z["vertices"], z["faces"], process=False)
    mesh = _sdf_mesh(sdf, lower, upper, spacing)
    if path:
        os.makedirs(MESH_CACHE[0], exist_ok=True)
        tmp = f"{path}.{os.getpid()}.npz"  # atomic: fits started together read no half-written file
        np.savez(tmp, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces))
        os.replace(tmp, path)
    return mesh


def _sdf_mesh(sdf, lower, upper, spacing: float) -> trimesh.Trimesh:
    from skimage.measure import marching_cubes

    # nodes off the planes the shapes are built on (no node exactly on the surface: no degenerate faces)
    lo, hi = np.asarray(lower, np.float64) + _GRID_OFFSET * spacing, np.asarray(upper, np.float64)
    axes = [np.arange(lo[k], hi[k] + 0.5 * spacing, spacing) for k in range(3)]
    vals = np.empty([len(a) for a in axes], np.float32)
    for i, x in enumerate(axes[0]):  # a slab at a time: bounded memory
        g = np.stack(np.meshgrid([x], axes[1], axes[2], indexing="ij"), -1)[0]
        vals[i] = sdf(g)
    v, f, _, _ = marching_cubes(vals, 0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(v + lo, f, process=True)
    if mesh.is_watertight and mesh.volume < 0:  # outward normals
        mesh.invert()
    return mesh


_GRID_OFFSET = 0.3819660  # of a cell: 2 - golden ratio, a fraction no plane of a shape here falls on


def _mug_sdf(p):
    body = _cylinder_z(p, (0, 0, 0.5), 0.5, 0.5)
    handle = _torus_y(p, (0.52, 0, 0.5), 0.27, 0.06)
    cavity = _cylinder_z(p, (0, 0, 0.68), 0.42, 0.6)  # from z = 0.08 up through the open top
    return np.maximum(np.minimum(body, handle), -cavity)


_LEG = 0.03  # half-width of legs and posts, half-thickness of the seat


def _chair_sdf(p):
    parts = [_box(p, (0, 0, 0.5), (0.4, 0.4, _LEG))]  # seat, top at z = 0.53
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(_box(p, (0.34 * sx, 0.34 * sy, 0.25), (_LEG, _LEG, 0.25)))  # legs, z 0 - 0.5
        parts.append(_box(p, (0.34 * sx, 0.34, 0.8), (_LEG, _LEG, 0.3)))  # back posts up to z = 1.1
    parts.append(_box(p, (0, 0.34, 1.04), (0.37, _LEG, 0.06)))  # top rail: seat, posts and rail close a loop
    return np.min(parts, axis=0)


def _bowl_sdf(p):
    shell = np.maximum(_sphere(p, (0, 0, 0.6), 0.6), -_sphere(p, (0, 0, 0.6), 0.52))
    return np.maximum(shell, p[..., 2] - 0.66)  # rim a little above the equator


def torus_mesh() -> trimesh.Trimesh:
    m = trimesh.creation.torus(major_radius=0.6, minor_radius=0.18, major_sections=96, minor_sections=48)
    m.apply_transform(trimesh.transformations.rotation_matrix(math.radians(30), (1, 0, 0)))
    return m


def mug_mesh() -> trimesh.Trimesh:
    return sdf_mesh(_mug_sdf, (-0.56, -0.56, -0.04), (0.9, 0.56, 1.04), 0.008)


def chair_mesh() -> trimesh.Trimesh:
    return sdf_mesh(_chair_sdf, (-0.45, -0.45, -0.03), (0.45, 0.45, 1.13), 0.006)


def bowl_mesh() -> trimesh.Trimesh:
    return sdf_mesh(_bowl_sdf, (-0.64, -0.64, -0.04), (0.64, 0.64, 0.7), 0.006)


def blob_mesh(seed: int = 3) -> trimesh.Trimesh:
    """An icosphere of radius 0.6 pushed in and out by 14 smooth random bumps (+-25 %)."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    n = np.asarray(m.vertices)
    c = rng.normal(size=(14, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    amp = rng.uniform(-0.25, 0.25, 14)
    r = 1.0 + (amp[None, :] * np.exp(-(1.0 - n @ c.T) / 0.08)).sum(1)
    return trimesh.Trimesh(0.6 * n * r[:, None], m.faces, process=False)


def _clip_plane(v: np.ndarray, f: np.ndarray, axis: int, bound: float, keep_above: bool):
    """Cut the indexed mesh ``(v, f)`` at the plane ``x[axis] = bound``, keeping one side; an edge
    shared by two faces is cut at one new vertex, so the result stays connected."""
    s = v[:, axis] - bound if keep_above else bound - v[:, axis]
    inside = s >= 0
    n_in = inside[f].sum(1)
    whole, cut = f[n_in == 3], f[(n_in == 1) | (n_in == 2)]
    if len(cut) == 0:
        return v, whole
    odd_in = inside[cut].sum(1) == 1  # the odd vertex is the one inside (else the one outside)
    odd = np.argmax(inside[cut] == odd_in[:, None], axis=1)
    rot = cut[np.arange(len(cut))[:, None], (odd[:, None] + np.arange(3)) % 3]  # odd vertex first, winding kept
    a, b, c = rot.T
    edges = np.sort(np.concatenate([np.stack([a, b], 1), np.stack([a, c], 1)]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    t = s[uniq[:, 0]] / (s[uniq[:, 0]] - s[uniq[:, 1]])
    new_v = v[uniq[:, 0]] + t[:, None] * (v[uniq[:, 1]] - v[uniq[:, 0]])
    e_ab, e_ac = np.split(len(v) + inv.reshape(-1), 2)
    tris = [np.stack([a, e_ab, e_ac], 1)[odd_in],  # one vertex inside: one triangle
            np.stack([e_ab, b, c], 1)[~odd_in], np.stack([e_ab, c, e_ac], 1)[~odd_in]]  # two: a quad
    return np.concatenate([v, new_v]), np.concatenate([whole, *tris])


def clip_to_box(mesh: trimesh.Trimesh, lower, upper) -> trimesh.Trimesh:
    """The part of ``mesh`` inside the axis-aligned box, faces cut exactly at its sides (open there)."""
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    for k in range(3):
        for bound, above in ((lower[k], True), (upper[k], False)):
            v, f = _clip_plane(v, f, k, float(bound), above)
    out = trimesh.Trimesh(v, f, process=True)  # merges a cut vertex that fell on an old one
    out.update_faces(out.nondegenerate_faces())
    out.remove_unreferenced_vertices()
    return out
