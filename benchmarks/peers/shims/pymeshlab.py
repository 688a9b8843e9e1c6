# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``pymeshlab`` (a ~100 MB wheel, over one device call's carry): what ``pgsr_dpsr`` calls.

Its ``utils/mesh_utils.py: clean_and_repair`` loads its initial mesh, closes holes
of fewer than ``maxholesize`` boundary edges, merges close vertices, removes duplicate vertices,
duplicate faces, unreferenced vertices and zero-area faces, computes face normals and reads the
matrices back. Our own numpy implementation of MeshLab's filters of those names, at their defaults:

* ``meshing_close_holes``: like MeshLab, refuses a mesh with a non-manifold edge (raises) and fills
  every boundary loop of fewer than ``maxholesize`` edges by ear cutting, without new vertices. Ears are
  cut convex-first, best-shaped first (MeshLab's trivial-ear order); an ear whose new edge already exists
  in the mesh is skipped. MeshLab's self-intersection test (``selfintersection``) is not reproduced.
* ``meshing_merge_close_vertices``: threshold 1/10000 of the bounding-box diagonal (MeshLab's default);
  greedy in vertex order, each kept vertex absorbs the not yet merged ones within the threshold.
* ``meshing_remove_duplicate_vertices`` (identical positions), ``meshing_remove_duplicate_faces`` (same
  vertex set, any order), ``meshing_remove_unreferenced_vertices``, ``meshing_remove_null_faces``
  (area exactly zero), ``compute_normal_per_face`` (unit normals, right-hand rule).

Any other filter raises.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Mesh", "MeshSet", "PercentageValue", "PureValue", "PyMeshLabException"]


class PyMeshLabException(RuntimeError):
    pass


class PureValue:
    def __init__(self, value: float):
        self.value = float(value)


class PercentageValue:
    """A percentage of the bounding-box diagonal."""

    def __init__(self, value: float):
        self.value = float(value)


class Mesh:
    """Vertices [n, 3] float64, faces [m, 3] int, optional vertex colours [n, 4] in [0, 1]."""

    def __init__(self, vertex_matrix=None, face_matrix=None, v_color_matrix=None):
        self.v = np.asarray(np.zeros((0, 3)) if vertex_matrix is None else vertex_matrix, np.float64).reshape(-1, 3)
        self.f = np.asarray(np.zeros((0, 3)) if face_matrix is None else face_matrix, np.int64).reshape(-1, 3)
        self.c = None if v_color_matrix is None else np.asarray(v_color_matrix, dtype=np.float64)
        self.fn = None

    def vertex_number(self) -> int:
        return len(self.v)

    def face_number(self) -> int:
        return len(self.f)

    def vertex_matrix(self) -> np.ndarray:
        return self.v.copy()

    def face_matrix(self) -> np.ndarray:
        return self.f.astype(np.int32)

    def face_normal_matrix(self) -> np.ndarray:
        return (_face_normals(self.v, self.f) if self.fn is None else self.fn).copy()

    def vertex_color_matrix(self) -> np.ndarray:
        if self.c is None:
            raise PyMeshLabException("the mesh has no vertex colours")
        return self.c.copy()

    # -- edits that keep the colours in step with the vertices

    def _keep_vertices(self, keep: np.ndarray) -> None:
        """Drop the vertices where ``keep`` is False (faces must not reference them)."""
        remap = np.cumsum(keep) - 1
        self.v = self.v[keep]
        if self.c is not None:
            self.c = self.c[keep]
        self.f = remap[self.f]

    def _keep_faces(self, keep: np.ndarray) -> None:
        self.f = self.f[keep]
        self.fn = None


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(ln > 0, n / np.where(ln > 0, ln, 1), 0.0)


def _read(path: str) -> Mesh:
    import trimesh
    m = trimesh.load(path, process=False, force="mesh")
    c = None
    if getattr(m.visual, "kind", None) == "vertex":
        c = np.asarray(m.visual.vertex_colors, dtype=np.float64) / 255.0
    return Mesh(m.vertices, m.faces, c)


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the rows of ``a`` [n, k]: the index of each distinct row's first occurrence, each row's group
    (as an index into those), and the group sizes (np.unique(axis=0) without its structured-array sort)."""
    order = np.lexsort(a.T[::-1])
    s = a[order]
    new = np.ones(len(a), bool)
    new[1:] = np.any(s[1:] != s[:-1], axis=1)
    group_sorted = np.cumsum(new) - 1
    group = np.empty(len(a), np.int64)
    group[order] = group_sorted
    first = np.full(group_sorted[-1] + 1 if len(a) else 0, len(a), np.int64)
    np.minimum.at(first, group, np.arange(len(a)))
    counts = np.bincount(group, minlength=len(first))
    return first, group, counts


# -- the filters

def _close_holes(m: Mesh, maxholesize: int = 30, **_ignored) -> None:
    f = m.f
    if len(f) == 0:
        return
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, group, counts = _unique_rows(np.sort(half, axis=1))
    if np.any(counts > 2):
        raise PyMeshLabException("Mesh has some not 2-manifold edges, filter requires edge manifoldness")
    border = half[counts[group] == 1]  # half-edges of an edge with one face: the hole boundaries
    if len(border) == 0:
        return
    n = int(max(len(m.v), f.max() + 1))
    nxt: dict[int, list[int]] = {}
    for a, b in border.tolist():
        nxt.setdefault(a, []).append(b)
    on_border = np.zeros(n, bool)
    on_border[border.reshape(-1)] = True
    inner = half[on_border[half[:, 0]] & on_border[half[:, 1]]]  # only these can join two border vertices
    edges = set(map(tuple, np.sort(inner, axis=1).tolist()))
    new_faces = []
    for start in list(nxt):
        while nxt.get(start):
            loop = [start]
            cur = nxt[start].pop()
            while cur != start and nxt.get(cur):
                loop.append(cur)
                cur = nxt[cur].pop()
            if cur != start or len(loop) >= maxholesize or len(loop) < 3:
                continue  # an open chain (non-manifold vertex) or a hole too large
            new_faces += _ear_cut(m.v, loop, edges)
    if new_faces:
        m.f = np.concatenate([m.f, np.asarray(new_faces, dtype=np.int64)])
        m.fn = None


def _ear_cut(v: np.ndarray, loop: list[int], edges: set) -> list[tuple[int, int, int]]:
    """Triangles filling the hole bounded by ``loop`` (vertex ids along the border half-edges).

    Each step cuts the best ear (convex first, then the best-shaped, the first of equals) whose new edge is not
    already in ``edges``; a cut changes only its two neighbours' ears, so only those are scored again.
    """
    faces = []
    ring = list(loop)
    pos = dict(zip(ring, v[ring].tolist()))
    # the fill's orientation: new faces run against the border half-edges, so their normals follow the
    # reversed loop's Newell normal
    p = v[ring[::-1]]
    nh = np.cross(p, np.roll(p, -1, axis=0)).sum(0).tolist()
    k3 = 2.0 * math.sqrt(3.0)

    def score(i: int) -> tuple[bool, float]:
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = pos[ring[i - 1]], pos[ring[i]], pos[ring[(i + 1) % len(ring)]]
        ux, uy, uz, wx, wy, wz = cx - ax, cy - ay, cz - az, bx - ax, by - ay, bz - az
        nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx  # (c - a) x (b - a)
        e2 = (wx * wx + wy * wy + wz * wz) + ((cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2) + (
            ux * ux + uy * uy + uz * uz)
        quality = k3 * math.sqrt(nx * nx + ny * ny + nz * nz) / e2 if e2 > 0 else 0.0  # 1 for an equilateral one
        return nx * nh[0] + ny * nh[1] + nz * nh[2] > 0, quality

    scores = [score(i) for i in range(len(ring))]
    while len(ring) > 3:
        best = -1
        for i in range(len(ring)):
            a, c = ring[i - 1], ring[(i + 1) % len(ring)]
            if (min(a, c), max(a, c)) in edges:
                continue  # the new edge would be a third face's on an existing edge
            if best < 0 or scores[i] > scores[best]:
                best = i
        if best < 0:
            return faces  # no ear can be cut without a non-manifold edge: leave the rest open
        a, b, c = ring[best - 1], ring[best], ring[(best + 1) % len(ring)]
        faces.append((a, c, b))  # contains b->a and c->b, the twins of the border half-edges a->b and b->c
        edges.add((min(a, c), max(a, c)))
        del ring[best]
        del scores[best]
        for i in (best - 1, best % len(ring)):  # a's ear and c's ear now span the new edge
            scores[i] = score(i)
    faces.append((ring[0], ring[2], ring[1]))
    return faces


def _merge_close_vertices(m: Mesh, threshold=None, **_ignored) -> None:
    if len(m.v) == 0:
        return
    diag = float(np.linalg.norm(m.v.max(0) - m.v.min(0)))
    if threshold is None:
        r = diag / 10000.0
    elif isinstance(threshold, PercentageValue):
        r = diag * threshold.value / 100.0
    elif isinstance(threshold, PureValue):
        r = threshold.value
    else:
        r = float(threshold)
    from scipy.spatial import cKDTree
    pairs = cKDTree(m.v).query_pairs(r, output_type="ndarray")
    if len(pairs) == 0:
        return
    nbrs: dict[int, list[int]] = {}
    for i, j in pairs.tolist():
        nbrs.setdefault(i, []).append(j)
        nbrs.setdefault(j, []).append(i)
    target = np.arange(len(m.v))
    merged = np.zeros(len(m.v), bool)
    for i in sorted(nbrs):
        if merged[i]:
            continue
        for j in nbrs[i]:
            if not merged[j]:  # a kept j < i would have absorbed i already
                target[j] = i
                merged[j] = True
    m.f = target[m.f]
    m._keep_vertices(~merged)
    m.fn = None


def _remove_duplicate_vertices(m: Mesh, **_ignored) -> None:
    if len(m.v) == 0:
        return
    first, group, _ = _unique_rows(m.v)
    target = first[group]
    if np.all(target == np.arange(len(m.v))):
        return
    m.f = target[m.f]
    m._keep_vertices(target == np.arange(len(m.v)))


def _remove_duplicate_faces(m: Mesh, **_ignored) -> None:
    if len(m.f) == 0:
        return
    first, _, _ = _unique_rows(np.sort(m.f, axis=1))
    keep = np.zeros(len(m.f), bool)
    keep[first] = True
    m._keep_faces(keep)


def _remove_unreferenced_vertices(m: Mesh, **_ignored) -> None:
    used = np.zeros(len(m.v), bool)
    used[m.f.reshape(-1)] = True
    if not used.all():
        m._keep_vertices(used)


def _remove_null_faces(m: Mesh, **_ignored) -> None:
    if len(m.f) == 0:
        return
    n = np.cross(m.v[m.f[:, 1]] - m.v[m.f[:, 0]], m.v[m.f[:, 2]] - m.v[m.f[:, 0]])
    m._keep_faces(np.any(n != 0, axis=1))


_FILTERS = {
    "meshing_close_holes": _close_holes,
    "meshing_merge_close_vertices": _merge_close_vertices,
    "meshing_remove_duplicate_vertices": _remove_duplicate_vertices,
    "meshing_remove_duplicate_faces": _remove_duplicate_faces,
    "meshing_remove_unreferenced_vertices": _remove_unreferenced_vertices,
    "meshing_remove_null_faces": _remove_null_faces,
}


class MeshSet:
    """A list of meshes with a current one, and the filters above."""

    def __init__(self):
        self._meshes: list[Mesh] = []

    def load_new_mesh(self, path: str) -> None:
        self._meshes.append(_read(path))

    def add_mesh(self, mesh: Mesh, name: str = "") -> None:
        self._meshes.append(mesh)

    def current_mesh(self) -> Mesh:
        if not self._meshes:
            raise PyMeshLabException("the MeshSet is empty")
        return self._meshes[-1]

    def mesh_number(self) -> int:
        return len(self._meshes)

    def apply_filter(self, name: str, **kwargs) -> dict:
        if name not in _FILTERS:
            raise PyMeshLabException(f"filter {name!r} is not in the peers benchmark's stand-in")
        _FILTERS[name](self.current_mesh(), **kwargs)
        return {}

    def compute_normal_per_face(self, **_ignored) -> dict:
        m = self.current_mesh()
        m.fn = _face_normals(m.v, m.f)
        return {}

    def __getattr__(self, name: str):
        if name in _FILTERS:
            return lambda **kwargs: self.apply_filter(name, **kwargs)
        raise AttributeError(name)
