# SPDX-License-Identifier: Apache-2.0
"""The outline offset (wtopo/geometry/outline.py): how far a mesh's silhouettes lie inside the masks, and the
final mesh moved by it (wtopo/fitting/_final_mesh.py)."""

from unittest import mock

import numpy as np
import pytest
import torch
import trimesh
from mesh_scenes import depths_of, ring_cameras

_R = 0.5


def _sphere(radius):
    return trimesh.creation.icosphere(subdivisions=5, radius=radius)


def _masks(mesh, cams):
    return [d > 0 for d in depths_of(mesh, cams)]


@pytest.mark.parametrize("delta", [0.006, -0.006, 0.0])
def test_outline_offset_measures_a_sphere_grown_or_shrunk_by_a_known_distance(delta):
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=6, radius=4.0, size=320)
    off = outline_offset(_sphere(_R).vertices, _sphere(_R).faces, cams, _masks(_sphere(_R + delta), cams))
    # a pixel here is 4 * 2 tan(0.45) / 320 = 0.012 at the centre: delta is half of one; the same icosphere (scaled)
    # makes the masks, so its facets cancel; what is left is the pixel grid's (+-20 % of delta at 320 px, 6 % at 640)
    assert list(off.views) == list(range(6))
    assert off.distance == pytest.approx(delta, abs=0.0015), (off.distance, off.pixels)
    if delta:
        assert np.sign(off.median_pixels) == np.sign(delta) and 0.3 < abs(off.median_pixels) < 0.8


def test_offset_along_normals_grows_a_closed_mesh_and_keeps_its_faces_and_colours():
    from wtopo.geometry.outline import offset_along_normals

    s = _sphere(_R)
    s.visual.vertex_colors = np.tile([10, 20, 30, 255], (len(s.vertices), 1))
    out = offset_along_normals(s, 0.01)
    r = np.linalg.norm(out.vertices, axis=1)
    assert np.allclose(r, _R + 0.01, atol=1e-6) and out.is_watertight
    assert np.array_equal(out.faces, s.faces) and np.array_equal(out.visual.vertex_colors, s.visual.vertex_colors)
    assert np.allclose(s.vertices, _sphere(_R).vertices)  # the input is left as it was
    assert offset_along_normals(s, 0.0).vertices.shape == s.vertices.shape


def test_outline_offset_leaves_out_views_cut_by_the_frame_and_tiny_masks():
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=4, radius=4.0, size=192)  # the sphere 25 px in radius: smooth limbs (< 9 px are edges)
    masks = _masks(_sphere(_R), cams)
    masks[1] = np.ones_like(masks[1])  # touches the border: the frame's outline, not the object's
    masks[2] = np.zeros_like(masks[2])
    masks[2][30:33, 30:33] = True  # 9 pixels
    off = outline_offset(_sphere(_R).vertices, _sphere(_R).faces, cams, masks)
    assert list(off.views) == [0, 3] and len(off.pixels) == 2
    none = outline_offset(_sphere(_R).vertices, _sphere(_R).faces, cams[1:2], masks[1:2])
    assert none.distance == 0.0 and len(none.views) == 0 and none.median_pixels == 0.0
    # float masks (a fit's, as torch tensors) threshold at 0.5
    soft = [torch.as_tensor(m, dtype=torch.float32) * 0.9 for m in _masks(_sphere(_R), cams)]
    assert outline_offset(_sphere(_R).vertices, _sphere(_R).faces, cams, soft).distance == pytest.approx(0.0, abs=2e-3)


def test_outline_offset_rejects_masks_that_do_not_match_the_cameras():
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=2, size=32)
    s = _sphere(_R)
    with pytest.raises(ValueError, match=r"one entry per camera \(2\), got 1"):
        outline_offset(s.vertices, s.faces, cams, [np.zeros((32, 32))])
    with pytest.raises(ValueError, match=r"masks\[1\] must have its camera's shape \(32, 32\), got \(16, 32\)"):
        outline_offset(s.vertices, s.faces, cams, [np.zeros((32, 32)), np.zeros((16, 32))])
    with pytest.raises(ValueError, match=r"masks\[0\] must be finite, got 1024 non-finite values"):
        outline_offset(s.vertices, s.faces, cams, [np.full((32, 32), np.nan), np.zeros((32, 32))])


def test_the_final_mesh_of_a_masked_object_moves_onto_the_masks_and_records_it():
    from wtopo.fitting._final_mesh import _OUTLINE_MAX_PIXELS, _outline

    cams = ring_cameras(n=6, radius=4.0, size=320)
    events = []
    record = lambda e, **k: events.append((e, k))  # noqa: E731
    out = _outline(_sphere(_R), cams, _masks(_sphere(_R + 0.006), cams), record=record, device=torch.device("cpu"))
    assert np.median(np.linalg.norm(out.vertices, axis=1)) == pytest.approx(_R + 0.006, abs=0.0015)
    name, info = events[0]
    assert name == "outline_offset" and info["views"] == 6 and 0.3 < info["pixels"] < 0.8
    assert info["distance"] == pytest.approx(np.median(np.linalg.norm(out.vertices, axis=1)) - _R, rel=0.01)
    # at most _OUTLINE_MAX_PIXELS footprints (0.012 here): masks 0.075 wider (about 6 px) move the mesh by one
    events.clear()
    far = _outline(_sphere(_R), cams, _masks(_sphere(_R + 0.075), cams), record=record, device=torch.device("cpu"))
    info = events[0][1]
    assert info["pixels"] > 4 and _OUTLINE_MAX_PIXELS == 1.0
    grown = float(np.median(np.linalg.norm(far.vertices, axis=1))) - _R
    assert grown == pytest.approx(info["distance"], rel=0.01) and 0.009 < grown < 0.016
    # no usable view: the mesh is returned as it was
    events.clear()
    same = _outline(_sphere(_R), cams[:1], [np.ones((320, 320), bool)], record=record, device=torch.device("cpu"))
    assert np.array_equal(same.vertices, _sphere(_R).vertices) and events[0][1]["views"] == 0


def test_a_thin_object_moves_inward_only():
    """A silhouette wider than the masks is too wide wherever it is; one short of them on thin parts is parts
    missing or rounded there (the held-out shelf), so a thin object's mesh never grows."""
    from wtopo.fitting._final_mesh import _outline

    cams = ring_cameras(n=6, radius=4.0, size=320)
    events = []
    record = lambda e, **k: events.append((e, k))  # noqa: E731
    same = _outline(_sphere(_R), cams, _masks(_sphere(_R + 0.006), cams), record=record, device=torch.device("cpu"),
                    thin=True)
    assert np.array_equal(same.vertices, _sphere(_R).vertices)
    assert events[0][1]["distance"] == 0.0 and events[0][1]["skipped"].startswith("thin parts")
    assert events[0][1]["pixels"] > 0
    events.clear()
    shrunk = _outline(_sphere(_R), cams, _masks(_sphere(_R - 0.006), cams), record=record, device=torch.device("cpu"),
                      thin=True)
    assert events[0][1]["distance"] < 0 and "skipped" not in events[0][1]
    assert np.median(np.linalg.norm(shrunk.vertices, axis=1)) == pytest.approx(_R - 0.006, abs=0.0015)


def test_outline_offset_is_the_median_over_views_of_unlike_footprints():
    """Each view's offset times its own footprint; the median keeps one view whose mask is far off out of it."""
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=3, radius=4.0, size=320) + ring_cameras(n=3, radius=6.0, size=320)
    masks = _masks(_sphere(_R + 0.006), cams)
    masks[1] = _masks(_sphere(_R + 0.06), cams[1:2])[0]  # one view's mask drawn about 5 px wide
    off = outline_offset(_sphere(_R).vertices, _sphere(_R).faces, cams, masks)
    near, far = off.footprints[[0, 2]], off.footprints[3:]
    assert np.all(far > 1.4 * near.max()), off.footprints  # the farther ring's pixels are larger
    assert off.pixels[1] > 3 and np.all(off.pixels[[0, 2, 3, 4, 5]] < 1)
    # the farther ring's silhouettes are 27 px in radius: its pixel grid reads 0.0078 (the mean of the six: 0.0155)
    assert off.distance == pytest.approx(0.006, abs=0.002), (off.distance, off.pixels)
    assert off.capped(1.0) == off.distance and off.capped(0.1) == pytest.approx(0.1 * np.median(off.footprints))


def test_a_move_that_does_not_bring_the_outline_closer_is_undone():
    """A mesh wound inward has normals that point in: growing it along them shrinks it, the silhouettes fall
    farther short of the masks, and the move is undone."""
    from wtopo.fitting._final_mesh import _outline

    cams = ring_cameras(n=6, radius=4.0, size=320)
    inverted = trimesh.Trimesh(_sphere(_R).vertices, _sphere(_R).faces[:, ::-1], process=False)
    events = []
    out = _outline(inverted, cams, _masks(_sphere(_R + 0.006), cams), record=lambda e, **k: events.append((e, k)),
                   device=torch.device("cpu"))
    info = events[0][1]
    assert np.array_equal(out.vertices, inverted.vertices) and info["distance"] == 0.0
    assert info["pixels"] > 0.3 and info["undone"] > info["pixels"], info


def test_non_finite_vertices_are_refused_by_the_measure_and_left_by_the_final_mesh():
    from wtopo.fitting._final_mesh import _outline
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=2, size=32)
    s = _sphere(_R)
    v = s.vertices.copy()
    v[3] = np.nan
    with pytest.raises(ValueError, match=r"verts must be finite, got 1 non-finite rows"):
        outline_offset(v, s.faces, cams, _masks(s, cams))
    events = []
    bad = trimesh.Trimesh(v, s.faces, process=False)
    assert _outline(bad, cams, _masks(s, cams), record=lambda e, **k: events.append((e, k)),
                    device=torch.device("cpu")) is bad
    assert events == [("outline_offset", {"skipped": "non-finite vertices", "distance": 0.0})]


def test_ridge_spread_is_zero_on_planes_small_on_a_wide_sphere_and_large_at_edges():
    from wtopo.geometry.outline import ridge_spread

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))  # 12 triangles, each far wider than a cell: sampled by area
    pts = np.array([[0.0, 0.0, 0.5], [0.2, -0.3, 0.5], [0.5, 0.0, 0.5], [0.5, 0.2, -0.5], [0.5, 0.5, 0.5]])
    s = ridge_spread(box.vertices, box.faces, pts, 0.05)
    assert s[0] == 0.0 and s[1] == 0.0, s  # inside a face: one normal
    assert np.all((s[2:4] > 0.2) & (s[2:4] <= 1 - np.sqrt(0.5) + 1e-9)), s  # on edges: at most 1 - cos 45 degrees
    assert 0.3 < s[4] <= 1 - np.sqrt(1 / 3) + 1e-9, s  # at a corner, three sides
    assert np.all(ridge_spread(box.vertices, box.faces, pts, 0.2) >= s - 1e-9)  # a wider box sees as much bending
    # a sphere of radius R, cells c: the 27 cells' normals spread about (1.5 c / R)^2 / 3 (about 0.001 here)
    sp = ridge_spread(_sphere(_R).vertices, _sphere(_R).faces, _sphere(_R).vertices, 0.03)
    assert np.all(sp < 0.01) and np.median(sp) == pytest.approx((1.5 * 0.03 / _R) ** 2 / 3, rel=0.6)
    # a point far from the surface or a mesh of no area: no surface in its box (NaN)
    assert np.isnan(ridge_spread(box.vertices, box.faces, [[3.0, 0.0, 0.0]], 0.05)).all()
    assert np.isnan(ridge_spread(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((1, 3)), 0.1)).all()
    assert np.isnan(ridge_spread(np.zeros((0, 3)), np.zeros((0, 3), int), np.zeros((2, 3)), 0.1)).all()
    assert ridge_spread(box.vertices, box.faces, np.zeros((0, 3)), 0.1).shape == (0,)
    with pytest.raises(ValueError, match=r"cell must be a positive distance, got 0.0"):
        ridge_spread(box.vertices, box.faces, pts, 0.0)
    with pytest.raises(ValueError, match=r"cell must be a positive distance, got nan"):
        ridge_spread(box.vertices, box.faces, pts, float("nan"))


def _rounded_box(half: float, radius: float, step: float) -> trimesh.Trimesh:
    """A cube of half-side ``half`` whose edges and corners are rounded to ``radius`` (marching cubes, ``step``)."""
    from skimage.measure import marching_cubes

    g = np.arange(-half - 3 * step, half + 3 * step + step / 2, step)
    q = np.abs(g) - (half - radius)
    x, y, z = q[:, None, None], q[None, :, None], q[None, None, :]
    outside = np.sqrt(np.maximum(x, 0) ** 2 + np.maximum(y, 0) ** 2 + np.maximum(z, 0) ** 2)
    sdf = outside + np.minimum(np.maximum(np.maximum(x, y), z), 0.0) - radius
    v, f, _, _ = marching_cubes(sdf, 0.0, spacing=(step,) * 3)
    return trimesh.Trimesh(v + g[0], f[:, ::-1], process=False)  # outward


def test_a_rounded_box_on_a_sharp_boxs_masks_is_not_moved():
    """The chair's case (design/decisions.md): a fit rounds a boxy object's edges while its faces lie on the truth.
    Its silhouettes, drawn by the edges, fall short of the masks everywhere, and counting every outline pixel reads
    that as a surface inside; the ridge test counts no edge rounded within its finer box (here 1.2 footprints), so
    the mesh stays. An edge rounded to several footprints is a smooth limb at the pixels' scale."""
    from wtopo.fitting._final_mesh import _outline
    from wtopo.geometry import outline

    cams = ring_cameras(n=6, radius=4.0, size=320)  # footprint about 0.012: edges rounded to 1.2 of them
    mesh = _rounded_box(0.4, 0.015, 0.005)
    assert mesh.is_watertight
    masks = _masks(trimesh.creation.box(extents=(0.8, 0.8, 0.8)), cams)
    with mock.patch.object(outline, "RIDGE_SPREAD", 2.0):  # every outline pixel a smooth limb
        every = outline.outline_offset(mesh.vertices, mesh.faces, cams, masks)
    assert len(every.views) == 6 and every.median_pixels > 0.3, every.pixels  # every view measurable
    off = outline.outline_offset(mesh.vertices, mesh.faces, cams, masks)
    assert np.all(off.shares < 0.3), off.shares
    assert abs(off.distance) < 0.15 * np.median(every.footprints), (off.distance, off.pixels, off.shares)
    events = []
    out = _outline(mesh, cams, masks, record=lambda e, **k: events.append(k), device=torch.device("cpu"))
    assert abs(events[0]["distance"]) < 0.15 * np.median(every.footprints), events
    assert np.abs(out.vertices - mesh.vertices).max() <= abs(events[0]["distance"]) + 1e-12


def test_the_offset_of_a_mesh_with_edges_and_smooth_limbs_is_the_smooth_limbs_own():
    """A sphere beside a box: the masks grow the sphere by 0.006 and draw the box as it is. The measure gives each
    missed pixel to the nearest outline pixel and counts the sphere's outline alone, so it reads the sphere's 0.006,
    not that spread over the box's outline as well."""
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=6, radius=5.0, size=400)
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.3)).subdivide().subdivide()
    box.apply_translation((0.0, 0.0, 0.75))  # above the sphere: both in every view of the ring
    mesh = trimesh.util.concatenate([_sphere(_R), box])
    masks = _masks(trimesh.util.concatenate([_sphere(_R + 0.006), box]), cams)
    off = outline_offset(mesh.vertices, mesh.faces, cams, masks)
    assert len(off.views) == 6 and np.all((off.shares > 0.5) & (off.shares < 0.95)), off.shares
    assert off.distance == pytest.approx(0.006, abs=0.0015), (off.distance, off.pixels)



def test_a_silhouette_that_spills_past_the_masks_counts_everywhere():
    """A rounded edge only draws an outline in: where the silhouettes spill past the masks, they are too wide
    wherever they are, edges included, so every outline pixel counts and a boxy mesh still shrinks onto them."""
    from wtopo.geometry.outline import outline_offset

    cams = ring_cameras(n=6, radius=4.0, size=320)
    mesh = _rounded_box(0.4, 0.015, 0.005)
    masks = _masks(trimesh.creation.box(extents=(0.78, 0.78, 0.78)), cams)  # 0.01 inside each face
    off = outline_offset(mesh.vertices, mesh.faces, cams, masks)
    assert len(off.views) == 6 and np.all(off.shares == 1.0), off.shares
    assert off.distance == pytest.approx(-0.01, abs=0.004), (off.distance, off.pixels)
