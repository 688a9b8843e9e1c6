# SPDX-License-Identifier: Apache-2.0
"""orient_faces: consistent winding by the double cover of the face graph, against trimesh's walk."""

import numpy as np
import pytest
import trimesh

from wtopo.fitting.tsdf import repair_mesh
from wtopo.geometry.winding import orient_faces


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
    assert ours.metadata["closed"] is True  # its own closedness test, kept for the final mesh's policy
    assert _oriented_like(ours.faces, theirs.faces).all()
    assert _oriented_like(ours.faces, s.faces).all()
    # an already consistent mesh of two parts, one inside out (a cavity), is left as it is by both
    inner = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    two = trimesh.Trimesh(np.concatenate([s.vertices, inner.vertices]),
                          np.concatenate([s.faces, inner.faces[:, ::-1] + len(s.vertices)]), process=False)
    theirs = two.copy()
    trimesh.repair.fix_normals(theirs)
    ours = repair_mesh(two.copy())
    assert (ours.faces == two.faces).all() and (theirs.faces == two.faces).all()
    # a hole larger than the loops it caps (a fine hemisphere's rim, over _FAN_MAX_EDGES): left open, and said so
    fine = trimesh.creation.icosphere(subdivisions=5)
    half = fine.faces[fine.triangles_center[:, 2] > 0.0]
    assert repair_mesh(trimesh.Trimesh(fine.vertices, half, process=False)).metadata["closed"] is False


def _inconsistent_edges(faces: np.ndarray) -> int:
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, inv, cnt = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    fwd = (directed[:, 0] < directed[:, 1]).astype(float)
    per = np.bincount(inv, weights=fwd, minlength=len(cnt))
    return int(np.sum((cnt == 2) & (per != 1)))


def _moebius(n: int = 24, offset: int = 0) -> np.ndarray:
    """A Moebius strip of 2n faces over vertices offset..offset + 2n - 1 (the half twist closes it)."""
    faces = []
    for i in range(n):
        a0, a1 = 2 * i, 2 * i + 1
        j = (i + 1) % n
        b0, b1 = (2 * j, 2 * j + 1) if j else (1, 0)
        faces += [(a0, b0, a1), (a1, b0, b1)]
    return np.asarray(faces) + offset


def test_moebius_strip_keeps_one_seam_and_a_glitch_does_not_stop_the_repair():
    """A Moebius strip cannot be wound consistently: it comes back with the one conflicting edge a walk
    around it must leave, and scrambled, no more. A large sheet with a third of its faces reversed and
    such a strip joined to it (one non-orientable part) is repaired everywhere but on the strip's seam."""
    strip = _moebius()
    assert _inconsistent_edges(strip) == 1
    rng = np.random.default_rng(4)
    assert _inconsistent_edges(orient_faces(_reverse(strip, rng.random(len(strip)) < 0.4))) == 1

    m = 30  # a 30 x 30 grid of vertices, two triangles per cell
    idx = np.arange(m * m).reshape(m, m)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    grid = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    mob = _moebius(offset=m * m)
    mob[mob == m * m] = idx[0, 0]  # the strip shares its first edge with the grid's corner cell
    mob[mob == m * m + 1] = idx[0, 1]
    faces = np.concatenate([grid, mob])
    scrambled = _reverse(faces, rng.random(len(faces)) < 0.3)
    assert _inconsistent_edges(scrambled) > 500
    out = orient_faces(scrambled)
    assert _inconsistent_edges(out) <= 2  # the twist's seam (where the strip joins, one more at most)
    assert _inconsistent_edges(out[:len(grid)]) == 0


def test_non_manifold_edges_single_and_degenerate_faces():
    """An edge of three faces constrains nothing: a fin on it keeps its winding either way, and the sphere
    beside it is oriented; a lone face keeps its winding; a face repeating a vertex neither crashes nor
    disturbs the rest."""
    s = trimesh.creation.icosphere(subdivisions=2)
    e = s.faces[0, :2]
    mask = np.zeros(len(s.faces) + 1, dtype=bool)
    mask[5:40] = True
    for fin in (np.array([[e[0], e[1], len(s.vertices)]]), np.array([[e[1], e[0], len(s.vertices)]])):
        faces = np.concatenate([fin, s.faces])  # first: an edge's first two faces in order include the fin
        out = orient_faces(_reverse(faces, mask))
        assert _oriented_like(out[1:], s.faces).all()
        assert (out[0] == fin[0]).all()
    lone = np.array([[2, 0, 1]])
    assert (orient_faces(lone) == lone).all()
    degenerate = np.concatenate([s.faces, [[0, 0, 1]]])
    out = orient_faces(_reverse(degenerate, mask))
    assert _oriented_like(out[:-1], s.faces).all()


def test_bad_faces_are_refused_and_empty_is_empty():
    with pytest.raises(ValueError, match=r"faces must have shape \[F, 3\]"):
        orient_faces(np.zeros((4, 4), dtype=int))
    with pytest.raises(ValueError, match="the index -1"):
        orient_faces(np.array([[0, 1, -1]]))
    assert orient_faces(np.zeros((0, 3), dtype=int)).shape == (0, 3)


def test_is_closed_boundary_edges_and_signed_volume_agree_with_trimesh():
    """The fast closedness test, the boundary edges and the signed volume against trimesh on closed meshes, on
    the same meshes with faces removed, and inside out."""
    import trimesh

    from wtopo.fitting.tsdf import signed_volume
    from wtopo.geometry.winding import boundary_edges, is_closed

    for mesh in (trimesh.creation.icosphere(subdivisions=2), trimesh.creation.box(), trimesh.creation.torus(1.0, 0.3)):
        assert is_closed(mesh.faces) and mesh.is_watertight and len(boundary_edges(mesh.faces)) == 0
        assert np.isclose(signed_volume(mesh), mesh.volume, rtol=1e-12)
        inside_out = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
        assert np.isclose(signed_volume(inside_out), -mesh.volume, rtol=1e-12)
        open_mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[2:], process=False)
        assert not is_closed(open_mesh.faces) and not open_mesh.is_watertight
        border = boundary_edges(open_mesh.faces)
        ref = open_mesh.edges[trimesh.grouping.group_rows(open_mesh.edges_sorted, require_count=1)]
        assert sorted(map(tuple, border.tolist())) == sorted(map(tuple, ref.tolist()))  # as the faces wind them
    tri = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 2]])  # an edge of three faces: not closed
    assert not is_closed(tri) and not is_closed(np.zeros((0, 3), np.int64))
