# SPDX-License-Identifier: Apache-2.0
"""orient_faces: consistent winding by the double cover of the face graph, against trimesh's walk."""

import numpy as np
import pytest
import trimesh

from wtopo.fitting.tsdf import repair_mesh
from wtopo.fitting.winding import orient_faces


def _reverse(faces: np.ndarray, mask: np.ndarray) -> np.ndarray:
    out = faces.copy()
    out[mask] = out[mask][:, ::-1]
    return out


def _oriented_like(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per face: whether ``a``'s and ``b``'s face (same vertex set) run the same way round."""
    def key(f):  # rotate each face so that its smallest index comes first
        r = np.argmin(f, axis=1)
        return np.stack([f[np.arange(len(f)), (r + k) % 3] for k in range(3)], axis=1)
    assert (np.sort(a, axis=1) == np.sort(b, axis=1)).all()
    return (key(a) == key(b)).all(axis=1)


def _consistent(faces: np.ndarray) -> bool:
    """Every edge of exactly two faces traversed in opposite directions (the closed-form check)."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    und = np.sort(directed, axis=1)
    _, inv, cnt = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    two = cnt[inv] == 2
    fwd = directed[:, 0] < directed[:, 1]
    # an edge of two faces is consistent when one traverses it forwards and the other backwards
    per = np.bincount(inv[two], weights=fwd[two].astype(float), minlength=len(cnt))
    return bool(np.all(per[cnt == 2] == 1))


def test_scrambled_closed_sphere_comes_back_as_given():
    """A third of a closed sphere's faces reversed: every one is turned back (the part's majority), the
    winding is consistent and the mesh encloses a positive volume."""
    s = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(0)
    mask = rng.random(len(s.faces)) < 0.33
    mask[0] = True  # the first face (where a graph search starts) among the minority
    out = orient_faces(_reverse(s.faces, mask))
    assert _oriented_like(out, s.faces).all()
    m = trimesh.Trimesh(s.vertices, out, process=False)
    assert m.is_winding_consistent and m.volume > 0


def test_open_patch_and_the_majority():
    """An open hemisphere with a fifth of its faces reversed: consistent across every interior edge, and
    the original orientation (the majority) kept; with four fifths reversed, the reversed one."""
    s = trimesh.creation.icosphere(subdivisions=3)
    keep = s.triangles_center[:, 2] > 0.1
    hemi = s.faces[keep]
    rng = np.random.default_rng(1)
    for frac, same in ((0.2, True), (0.8, False)):
        mask = rng.random(len(hemi)) < frac
        mask[0] = not same  # the first face against the majority
        scrambled = _reverse(hemi, mask)
        assert not _consistent(scrambled)
        out = orient_faces(scrambled)
        assert _consistent(out)
        agree = _oriented_like(out, hemi)
        assert agree.all() if same else (~agree).all()


def test_each_part_keeps_its_own_orientation_and_a_cavity_stays_inwards():
    """Two disjoint closed shells, one inside the other and wound inwards (a cavity, as marching cubes
    winds it): each part is fixed on its own and the cavity is not turned outwards."""
    outer = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    faces = np.concatenate([outer.faces, inner.faces[:, ::-1] + len(outer.vertices)])
    rng = np.random.default_rng(2)
    mask = rng.random(len(faces)) < 0.25
    mask[[0, len(outer.faces)]] = True  # each part's first face among the minority
    out = orient_faces(_reverse(faces, mask))
    assert _oriented_like(out, faces).all()
    verts = np.concatenate([outer.vertices, inner.vertices])
    m = trimesh.Trimesh(verts, out, process=False)
    assert m.volume == pytest.approx(outer.volume - inner.volume, rel=1e-9)


def test_repair_turns_a_closed_inside_out_mesh_and_matches_trimesh():
    """repair_mesh: a closed sphere wound inwards, a tenth of it scrambled, comes back outwards, the faces
    wound as trimesh's fix_normals (the walk it replaced) winds them."""
    s = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(3)
    inside_out = _reverse(s.faces, rng.random(len(s.faces)) < 0.9)
    ours = repair_mesh(trimesh.Trimesh(s.vertices, inside_out, process=False))
    theirs = trimesh.Trimesh(s.vertices, inside_out, process=False)
    trimesh.repair.fix_normals(theirs)
    assert ours.is_winding_consistent and ours.volume > 0
    assert _oriented_like(ours.faces, theirs.faces).all()
    assert _oriented_like(ours.faces, s.faces).all()


def test_moebius_strip_is_left_as_given_and_non_manifold_edges_constrain_nothing():
    """A Moebius strip cannot be wound consistently: its faces come back unchanged. A fin on a third face
    of one edge (non-manifold) leaves the rest to be oriented."""
    n = 24
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    verts = []
    for a in t:
        for w in (-0.2, 0.2):
            r = 1 + w * np.cos(a / 2)
            verts.append((r * np.cos(a), r * np.sin(a), w * np.sin(a / 2)))
    faces = []
    for i in range(n):
        a0, a1 = 2 * i, 2 * i + 1
        j = (i + 1) % n
        b0, b1 = (2 * j, 2 * j + 1) if j else (1, 0)  # the half twist closes the strip
        faces += [(a0, b0, a1), (a1, b0, b1)]
    faces = np.asarray(faces)
    assert (orient_faces(faces) == faces).all()

    s = trimesh.creation.icosphere(subdivisions=2)
    e = s.faces[0, :2]
    fin = np.array([[e[0], e[1], len(s.vertices)]])
    faces = np.concatenate([s.faces, fin])
    mask = np.zeros(len(faces), dtype=bool)
    mask[5:40] = True
    out = orient_faces(_reverse(faces, mask))
    assert _oriented_like(out[:-1], s.faces).all()


def test_bad_faces_are_refused_and_empty_is_empty():
    with pytest.raises(ValueError, match=r"faces must have shape \[F, 3\]"):
        orient_faces(np.zeros((4, 4), dtype=int))
    with pytest.raises(ValueError, match="the index -1"):
        orient_faces(np.array([[0, 1, -1]]))
    assert orient_faces(np.zeros((0, 3), dtype=int)).shape == (0, 3)
