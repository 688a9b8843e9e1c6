# SPDX-License-Identifier: Apache-2.0
"""The meshing policy: components kept by view support (never by rank), no face near a camera."""

import numpy as np
import pytest
import trimesh
from mesh_scenes import depths_of, pair_lone_and_speck, ring_cameras, seen_pair

from wtopo import Camera
from wtopo.geometry.mesh_policy import crop_near_cameras, crop_to_box, supported_components, supported_faces
from wtopo.metrics import camera_clearance


def test_two_objects_are_both_kept_and_an_unseen_floater_goes():
    """Keep a torus and a capsule the views see; drop a speck that no rendered depth supports."""
    seen = seen_pair()
    cams = ring_cameras()
    depths = depths_of(seen, cams)  # the speck is not in the rendered depth: no view supports it
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    speck.apply_translation([0, 0, 1.2])
    mesh, info = supported_components(trimesh.util.concatenate([seen, speck]), cams, depths)
    assert info["components"] == 3 and info["kept"] == 2
    assert len(info["dropped"]) == 1 and info["dropped"][0]["views"] < 3
    assert len(mesh.split(only_watertight=False)) == 2
    np.testing.assert_allclose(mesh.area, seen.area, rtol=1e-9)


def _support_views_exhaustive(mesh, cams, depths):
    """Reference: every view tested on every vertex of every component (the rule without early exit)."""
    from reference.vertex_support import view_agreement_numpy

    from wtopo.geometry import mesh_policy as mp

    label = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    vlabel = np.full(len(mesh.vertices), -1)
    vlabel[np.asarray(mesh.faces).reshape(-1)] = np.repeat(label, 3)
    n = label.max() + 1
    vcount = np.bincount(vlabel[vlabel >= 0], minlength=n)
    views = np.zeros(n, int)
    for c, d in zip(cams, depths):
        agree = view_agreement_numpy(np.asarray(mesh.vertices), c, d) & (vlabel >= 0)
        views += np.bincount(vlabel[agree], minlength=n) / np.maximum(vcount, 1) >= mp._SUPPORT_VERTEX_FRACTION
    return views


def test_support_stops_testing_decided_components_without_changing_the_result():
    """Keep and drop exactly the components the exhaustive rule does, with the same counts for the dropped
    ones, on a scene with a seen pair, a floater and a component only two views support."""
    from wtopo.geometry import mesh_policy as mp

    cams = ring_cameras()
    mesh, seen, depths = pair_lone_and_speck(cams)
    views = _support_views_exhaustive(mesh, cams, depths)
    out, info = supported_components(mesh, cams, depths)
    share = np.bincount(trimesh.graph.connected_component_labels(mesh.face_adjacency), weights=mesh.area_faces)
    share = share / share.sum()
    keep = (views >= mp._MIN_SUPPORT_VIEWS) & (share >= mp._MIN_AREA_FRACTION)
    assert info["kept"] == int(keep.sum()) == 2 and info["components"] == 4
    order = np.argsort(-share)
    assert [d["views"] for d in info["dropped"]] == [int(views[c]) for c in order if not keep[c]]
    assert any(d["views"] == 2 for d in info["dropped"])  # the component two views see was tested fully
    np.testing.assert_allclose(out.area, seen.area, rtol=1e-9)


def test_camera_clearance_is_the_exact_point_to_triangle_distance():
    """Match a brute-force closest-point query, including a camera facing a large triangle's interior."""
    tri = trimesh.Trimesh([[-10, -10, 0], [10, -10, 0], [0, 10, 0]], [[0, 1, 2]])
    centers = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -2.0], [30.0, 0.0, 0.0]])
    got = camera_clearance(tri, centers)
    tris = np.asarray(tri.triangles)
    ref = np.array([np.linalg.norm(trimesh.triangles.closest_point(tris, c[None])[0] - c) for c in centers])
    np.testing.assert_allclose(got, ref, rtol=1e-9)
    assert got[0] == pytest.approx(0.3)  # far from every vertex (> 10), close to the face


def test_faces_near_a_camera_are_removed_and_only_those():
    """Remove the faces within ``near`` of a camera centre, keep the rest."""
    plane = trimesh.creation.box([4.0, 4.0, 0.01])
    plane = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(plane.vertices, plane.faces, 0.2))
    centers = np.array([[0.0, 0.0, 0.1], [5.0, 5.0, 5.0]])
    out, removed = crop_near_cameras(plane, centers, 0.5)
    assert removed > 0 and len(out.faces) == len(plane.faces) - removed
    assert camera_clearance(out, centers)[0] >= 0.5
    assert camera_clearance(plane, centers)[0] < 0.5


def test_faces_near_a_camera_match_the_exhaustive_test_whatever_the_cameras():
    """Cameras far from the mesh's box are skipped before any per-face work: the faces removed are exactly those an
    exhaustive point-to-triangle test over every camera finds, for cameras near, inside and far from the box."""
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    near = 0.3
    centers = np.concatenate([rng.normal(size=(6, 3)) * 0.7,  # inside or near the sphere's box
                              rng.normal(size=(6, 3)) + np.array([4.0, 0.0, 0.0]),  # far from it
                              [[1.2, 0.0, 0.0], [0.0, 0.0, -1.25]]])  # just outside a face, within near
    tris = np.asarray(sphere.triangles)
    exhaustive = np.zeros(len(tris), bool)
    for c in centers:
        closest = trimesh.triangles.closest_point(tris, np.broadcast_to(c, (len(tris), 3)))
        exhaustive |= np.linalg.norm(closest - c, axis=1) < near
    out, removed = crop_near_cameras(sphere, centers, near)
    assert removed == int(exhaustive.sum()) > 0
    np.testing.assert_allclose(np.sort(np.asarray(out.triangles).reshape(-1, 9), axis=0),
                               np.sort(tris[~exhaustive].reshape(-1, 9), axis=0))
    far_only = centers[6:12]
    same, none = crop_near_cameras(sphere, far_only, near)
    assert none == 0 and same is sphere


def test_crop_to_box_keeps_faces_inside():
    """Keep exactly the faces whose vertices lie in the box."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    out = crop_to_box(s, [-2, -2, 0.0], [2, 2, 2])
    assert 0 < len(out.faces) < len(s.faces)
    assert out.vertices[:, 2].min() >= 0.0

def test_face_components_label_faces_that_share_a_vertex_together():
    """Separate parts get their own labels (as trimesh's edge adjacency gives them), two tetrahedra that share
    only a vertex are one component, unreferenced vertices are no component, and no faces give none."""
    from wtopo.geometry.components import face_components

    a = trimesh.creation.icosphere(subdivisions=2)
    parts = [a.copy() for _ in range(3)]
    for k, p in enumerate(parts):
        p.apply_translation([3.0 * k, 0.0, 0.0])
    mesh = trimesh.util.concatenate(parts)
    n, label = face_components(np.asarray(mesh.faces), len(mesh.vertices) + 5)  # 5 vertices no face uses
    ref = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    assert n == 3 and label.shape == (len(mesh.faces),) and set(label.tolist()) == {0, 1, 2}
    assert len({(x, y) for x, y in zip(label.tolist(), ref.tolist())}) == 3  # the same partition as trimesh's
    tet = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
    pinched = np.concatenate([tet, tet + 3])  # the second tetrahedron's vertex 0 is the first's vertex 3
    n, label = face_components(pinched, 7)
    assert n == 1 and (label == 0).all()
    assert face_components(np.zeros((0, 3), np.int64), 4)[0] == 0


def _grid(size, n, z):
    """A square [-size/2, size/2]^2 at height z, n x n cells of two triangles."""
    t = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    f = np.concatenate([np.stack([i, i + n + 1, i + 1], -1).reshape(-1, 3),
                        np.stack([i + 1, i + n + 1, i + n + 2], -1).reshape(-1, 3)])
    return trimesh.Trimesh(v, f, process=False)


def test_supported_faces_drop_a_sheet_no_view_shows_and_keep_what_they_see():
    """A ground seen by a ring of cameras and a sheet hung under it (in none of the rendered depths): the sheet's
    faces go, the ground's stay; a face needs min_views views at each vertex, within the tolerance."""
    ground = _grid(1.0, 20, 0.0)
    sheet = _grid(0.4, 8, -0.2)  # under the ground: every view sees the ground there instead
    cams = [Camera.look_at(np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 2.5]), np.zeros(3), np.array([0, 0, 1.0]),
                           fov_x=0.9, width=128, height=128) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    depths = depths_of(ground, cams)
    both = trimesh.util.concatenate([ground, sheet])
    kept, info = supported_faces(both, cams, depths, tolerance=0.05)
    assert info["faces"] == len(both.faces) and len(kept.faces) == info["kept"] >= 0.9 * len(ground.faces)
    np.testing.assert_allclose(kept.vertices[:, 2], 0.0)  # nothing of the sheet is left
    # of the ground only faces at its edge go (a vertex there falls on pixels half off the ground in some views)
    kept_centres = {tuple(c) for c in np.round(kept.triangles_center, 9)}
    inner = np.abs(ground.triangles_center[:, :2]).max(axis=1) < 0.45
    assert all(tuple(c) in kept_centres for c in np.round(ground.triangles_center[inner], 9))
    none, info = supported_faces(ground, cams, depths, tolerance=0.05, min_views=len(cams) + 1)
    assert info["kept"] == 0 and len(none.faces) == 0
    inner_mesh = _grid(0.8, 16, 0.0)
    assert supported_faces(inner_mesh, cams, depths, tolerance=0.05)[0] is inner_mesh  # nothing to drop: the input
    # regions: the sheet (0.16) goes at a smaller least area and stays at a larger one; the ground's few edge faces
    # that fail are small regions and stay
    kept, _ = supported_faces(both, cams, depths, tolerance=0.05, min_region_area=0.1)
    assert np.allclose(kept.vertices[:, 2], 0.0) and len(kept.faces) == len(ground.faces)
    kept, _ = supported_faces(both, cams, depths, tolerance=0.05, min_region_area=0.2)
    assert kept is both


@pytest.mark.parametrize("kwargs, match", [({"tolerance": 0.0}, "tolerance"),
                                           ({"tolerance": float("nan")}, "tolerance"),
                                           ({"tolerance": 0.05, "min_views": 0}, "min_views"),
                                           ({"tolerance": 0.05, "min_views": 2.5}, "min_views"),
                                           ({"tolerance": 0.05, "min_region_area": -1.0}, "min_region_area")])
def test_supported_faces_name_a_bad_argument(kwargs, match):
    cam = Camera.look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3), np.array([0, 1.0, 0]), fov_x=0.9, width=8, height=8)
    with pytest.raises(ValueError, match=match):
        supported_faces(_grid(1.0, 2, 0.0), [cam], [np.ones((8, 8))], **kwargs)
    with pytest.raises(ValueError, match="one map per camera"):
        supported_faces(_grid(1.0, 2, 0.0), [cam, cam], [np.ones((8, 8))], tolerance=0.05)


def test_support_rules_decide_the_same_on_every_device_as_the_numpy_projection(device):
    """The support rules' projection (:func:`wtopo.vertex_support.view_agreement`) agrees with the NumPy reference
    vertex by vertex on ``device`` (one camera with lens distortion; a listed subset with repeats; float32 and
    float64 depth maps); supported_components and supported_faces on ``device`` keep exactly the faces they keep
    on the CPU, with the same counts."""
    import dataclasses

    import torch
    from reference.vertex_support import view_agreement_numpy

    from wtopo.vertex_support import view_agreement

    cams = ring_cameras()
    cams[3] = dataclasses.replace(cams[3], distortion=np.array([0.05, -0.01, 0.001, 0.0005, 0.0]))
    mesh, _, depths = pair_lone_and_speck(cams)
    verts = np.asarray(mesh.vertices)
    vt = torch.as_tensor(verts, dtype=torch.float64, device=device)
    every = torch.arange(len(verts), device=device)
    some = torch.as_tensor(np.random.default_rng(0).integers(0, len(verts), 500), device=device)
    for c, d in zip(cams, depths):
        for tol in (None, 0.05):
            ref = view_agreement_numpy(verts, c, d, tol)
            assert ref.any()
            for dtype in (torch.float64, torch.float32):
                dd = torch.as_tensor(d, dtype=dtype, device=device)
                want = ref if dtype == torch.float64 else view_agreement_numpy(verts, c, dd.cpu().numpy(), tol)
                got = view_agreement(vt, every, c, dd, tolerance=tol)
                np.testing.assert_array_equal(got.cpu().numpy(), want)
                np.testing.assert_array_equal(view_agreement(vt, some, c, dd, tolerance=tol).cpu().numpy(),
                                              want[some.cpu().numpy()])
    ref, ref_info = supported_components(mesh, cams, depths)
    out, info = supported_components(mesh, cams, depths, device=device)
    assert info == ref_info and ref_info["kept"] == 2
    np.testing.assert_array_equal(out.faces, ref.faces)

    ground = _grid(1.0, 20, 0.0)
    both = trimesh.util.concatenate([ground, _grid(0.4, 8, -0.2)])
    ring = [Camera.look_at(np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 2.5]), np.zeros(3), np.array([0, 0, 1.0]),
                           fov_x=0.9, width=128, height=128) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    gd = depths_of(ground, ring)
    for kwargs in ({}, {"min_region_area": 0.1}, {"min_views": 2}):
        ref, ref_info = supported_faces(both, ring, gd, tolerance=0.05, **kwargs)
        out, info = supported_faces(both, ring, gd, tolerance=0.05, device=device, **kwargs)
        assert info == ref_info and ref_info["kept"] < len(both.faces)
        np.testing.assert_array_equal(out.faces, ref.faces)


def test_keep_faces_and_face_areas_match_trimesh():
    """The policy's own face selection and areas give what trimesh's copy / update_faces /
    remove_unreferenced_vertices and ``area_faces`` give: the same vertices, faces, vertex colours and metadata."""
    from wtopo.geometry.mesh_policy import _face_areas, keep_faces

    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh = trimesh.Trimesh(mesh.vertices * [1.0, 2.0, 0.5], mesh.faces, process=False)
    rng = np.random.default_rng(3)
    mesh.visual.vertex_colors = rng.integers(0, 256, (len(mesh.vertices), 4), dtype=np.uint8)
    mesh.metadata["closed"] = True
    keep = rng.random(len(mesh.faces)) < 0.4
    ref = mesh.copy()
    ref.update_faces(keep)
    ref.remove_unreferenced_vertices()
    out = keep_faces(mesh, keep)
    assert np.array_equal(out.vertices, ref.vertices) and np.array_equal(out.faces, ref.faces)
    assert np.array_equal(out.visual.vertex_colors, ref.visual.vertex_colors)
    assert out.metadata["closed"] is True and len(mesh.faces) == 1280  # the input is unchanged
    np.testing.assert_allclose(_face_areas(mesh), mesh.area_faces, rtol=1e-12, atol=0)
    some = np.flatnonzero(keep)
    np.testing.assert_allclose(_face_areas(mesh, some), mesh.area_faces[some], rtol=1e-12, atol=0)
    plain = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)  # no colours: none made up
    assert keep_faces(plain, keep).visual.kind is None
    faced = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False,
                            face_colors=rng.integers(0, 256, (len(mesh.faces), 4), dtype=np.uint8))
    ref = faced.copy()
    ref.update_faces(keep)
    ref.remove_unreferenced_vertices()
    assert np.array_equal(keep_faces(faced, keep).visual.face_colors, ref.visual.face_colors)


def test_cleanup_without_weld_matches_trimesh():
    """``cleanup_mesh(weld=False)`` keeps what trimesh's copy, ``update_faces`` and ``remove_unreferenced_vertices``
    keep: the faces that repeat no index, their vertices in order, the vertex colours; the input is unchanged."""
    from wtopo.fitting.tsdf import cleanup_mesh

    rng = np.random.default_rng(4)
    v = rng.random((60, 3))
    f = rng.integers(0, 50, (90, 3))  # vertices 50-59 unused; some faces repeat an index
    f[::7, 1] = f[::7, 0]
    cols = rng.integers(0, 255, (60, 4), dtype=np.uint8)
    raw = trimesh.Trimesh(v, f, vertex_colors=cols, process=False)
    ref = raw.copy()
    ref.update_faces((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    ref.remove_unreferenced_vertices()
    out = cleanup_mesh(raw, largest_component=False, repair=False, weld=False)
    assert np.array_equal(out.faces, ref.faces) and np.array_equal(out.vertices, ref.vertices)
    assert np.array_equal(out.visual.vertex_colors, ref.visual.vertex_colors)
    assert len(raw.faces) == 90 and len(raw.vertices) == 60  # the input is left as it was
