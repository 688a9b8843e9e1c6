# SPDX-License-Identifier: Apache-2.0
"""The peers benchmark's ``pymeshlab`` stand-in (``benchmarks/peers/shims/pymeshlab.py``), which fills the holes
of the TopoSurfel authors' initial mesh: holes below the size limit close with faces oriented as their
neighbours, larger ones stay open, a non-manifold edge is refused as MeshLab refuses it, and the ear order equals
the plain version that scores every ear at every step."""

from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

_PATH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "peers", "shims",
                     "pymeshlab.py")
_spec = importlib.util.spec_from_file_location("peers_pymeshlab_standin", _PATH)
pml = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pml)


def _sphere_with_holes(seed: int, fans: int = 6, lone_faces: int = 4, noise: float = 0.01):
    """An icosphere (radius 1) with a few vertex fans (holes of 5-6 edges) and single faces (3 edges) removed: the
    vertices, the faces kept, the faces removed and the number of fans removed."""
    rng = np.random.default_rng(seed)
    removed_fans = 0
    s = trimesh.creation.icosphere(subdivisions=3)
    v = s.vertices * (1 + noise * rng.standard_normal((len(s.vertices), 1)))
    f = np.asarray(s.faces, np.int64)
    drop = np.zeros(len(f), bool)
    used = np.zeros(len(v), bool)
    for c in rng.choice(len(v), size=4 * fans, replace=False):
        fan = np.any(f == c, axis=1)
        ring = np.unique(f[fan])
        if used[ring].any() or len(set(ring.tolist())) < 6:
            continue
        drop |= fan
        used[ring] = True
        removed_fans += 1
        if removed_fans == fans:
            break
    for i in rng.permutation(len(f)):
        if lone_faces == 0:
            break
        if not used[f[i]].any() and not drop[i]:
            drop[i] = True
            used[f[i]] = True
            lone_faces -= 1
    return v, f[~drop], f[drop], removed_fans


def _directed_edges(f: np.ndarray) -> np.ndarray:
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def _close(v, f, **kw):
    ms = pml.MeshSet()
    ms.add_mesh(pml.Mesh(v, f))
    ms.meshing_close_holes(**kw)
    return ms.current_mesh().face_matrix().astype(np.int64)


@pytest.mark.parametrize("seed", [0, 1])
def test_small_holes_close_watertight_and_outward(seed):
    v, f, dropped, fans = _sphere_with_holes(seed)
    assert fans == 6
    out = _close(v, f, maxholesize=30)
    assert np.array_equal(out[: len(f)], f)  # the mesh's own faces are kept as they were
    # a hole of L edges takes L - 2 faces: a lone face's hole one, a fan of k faces' hole k - 2
    assert len(out) == len(f) + len(dropped) - 2 * fans
    d = _directed_edges(out)
    assert len(np.unique(d, axis=0)) == len(d)  # each directed edge once: consistently oriented, manifold
    assert len(np.unique(np.sort(d, axis=1), axis=0)) * 2 == len(d)  # each edge has two faces: watertight
    new = out[len(f):]
    n = np.cross(v[new[:, 1]] - v[new[:, 0]], v[new[:, 2]] - v[new[:, 0]])
    assert np.all(np.einsum("ij,ij->i", n, v[new].mean(1)) > 0)  # the sphere's faces point outwards


def test_a_hole_at_the_size_limit_stays_open():
    v, f, dropped, _ = _sphere_with_holes(0, fans=1, lone_faces=0)
    assert len(dropped) in (5, 6)  # one fan: a hole of as many edges
    assert len(_close(v, f, maxholesize=len(dropped))) == len(f)
    assert len(_close(v, f, maxholesize=len(dropped) + 1)) == len(f) + len(dropped) - 2


def test_a_non_manifold_edge_is_refused():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three faces on the edge 0-1
    with pytest.raises(pml.PyMeshLabException, match="2-manifold"):
        _close(v, f)


def _ear_cut_every_ear_every_step(v, loop, edges):
    """The plain version: at every step, score every ear afresh and cut the best one whose edge is free."""
    faces, ring = [], list(loop)
    p = v[ring[::-1]]
    nh = np.cross(p, np.roll(p, -1, axis=0)).sum(0)
    while len(ring) > 3:
        best = None
        for i in range(len(ring)):
            a, b, c = ring[i - 1], ring[i], ring[(i + 1) % len(ring)]
            if (min(a, c), max(a, c)) in edges:
                continue
            nrm = np.cross(v[c] - v[a], v[b] - v[a])
            e2 = ((v[b] - v[a]) ** 2).sum() + ((v[c] - v[b]) ** 2).sum() + ((v[a] - v[c]) ** 2).sum()
            score = (float(nrm @ nh) > 0, 2 * np.sqrt(3) * np.linalg.norm(nrm) / e2 if e2 > 0 else 0.0)
            if best is None or score > best[0]:
                best = (score, (a, c, b), i)
        if best is None:
            return faces
        _, tri, i = best
        faces.append(tri)
        edges.add((min(tri[0], tri[1]), max(tri[0], tri[1])))
        del ring[i]
    faces.append((ring[0], ring[2], ring[1]))
    return faces


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_the_ear_order_equals_scoring_every_ear_at_every_step(seed, monkeypatch):
    # rougher holes than the tests above (noise 0.2, wide fans), where ears compete and some are concave
    v, f, _, _ = _sphere_with_holes(seed, fans=8, lone_faces=6, noise=0.2)
    fast = _close(v, f, maxholesize=60)
    monkeypatch.setattr(pml, "_ear_cut", _ear_cut_every_ear_every_step)
    assert np.array_equal(fast, _close(v, f, maxholesize=60))


def test_an_unknown_filter_is_refused():
    ms = pml.MeshSet()
    ms.add_mesh(pml.Mesh(np.eye(3), [[0, 1, 2]]))
    with pytest.raises(pml.PyMeshLabException, match="not in the peers benchmark"):
        ms.apply_filter("meshing_isotropic_explicit_remeshing")
