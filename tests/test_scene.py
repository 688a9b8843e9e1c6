# SPDX-License-Identifier: Apache-2.0
"""Scene validation, Similarity maps, normalisation invariance, subset/downscale, save round trip."""

import numpy as np
import pytest
import torch

from wtopo import Camera, load_scene, scenes
from wtopo.scene import NORMALIZATION_MARGIN, Scene, Similarity

# float64 host maths of a similarity then its inverse: a few ulps of the largest coordinate (1e4)
ROUNDTRIP_TOL = 1e-9
# normalised cameras of a rescaled / shifted copy of a scene: world maths in float64 at 1e4 offset
# and 1e-3 scale leaves ~1e-16 * 1e4 / 1e-3 / (scene extent) ~ 1e-9 relative error
INVARIANCE_TOL = 1e-7
PNG_TOL = 0.5 / 255 + 1e-6  # 8-bit PNG quantisation of colours in [0, 1]


@pytest.fixture(scope="module")
def sphere_scene():
    return scenes.load("sphere")


def _ring(n=6, size=(24, 20)):
    return [Camera.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0], [0, 0, 1], fov_x=0.8,
                           width=size[0], height=size[1]) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def _images(n, size=(24, 20)):
    return np.zeros((n, size[1], size[0], 3), np.float32)


@pytest.mark.parametrize("bad, match", [
    ("nan", r"cameras\[2\].*finite.*nan"),
    ("skewed_rotation", r"cameras\[2\].*orthonormal"),
    ("reflection", r"cameras\[2\].*det"),
    ("focal", r"cameras\[2\].*focal.*-5"),
    ("size", r"cameras\[2\].*size 30x20"),
])
def test_bad_camera_names_index_and_value(bad, match):
    """Reject a NaN, non-orthonormal, reflected, negative-focal or wrongly sized camera by index."""
    cams = _ring()
    c = cams[2]
    if bad == "nan":
        c.world_to_camera[1, 3] = np.nan
    elif bad == "skewed_rotation":
        c.world_to_camera[:3, :3] *= 1.1
    elif bad == "reflection":
        c.world_to_camera[0, :3] *= -1
    elif bad == "focal":
        c.K[0, 0] = -5.0
    else:
        cams[2] = _ring(size=(30, 20))[2]
    with pytest.raises(ValueError, match=match):
        Scene(cams, _images(6))


def test_bad_arrays_are_rejected():
    """Reject images out of range, wrong mask shapes, negative depths and bad bounds."""
    cams = _ring()
    im = _images(6)
    im[3, 4, 5, 1] = 1.5
    with pytest.raises(ValueError, match=r"images must be in \[0, 1\].*1.5.*image 3"):
        Scene(cams, im)
    with pytest.raises(ValueError, match="images must have shape"):
        Scene(cams, _images(5))
    with pytest.raises(ValueError, match="masks must have shape"):
        Scene(cams, _images(6), masks=np.ones((6, 4, 4), bool))
    d = np.ones((6, 20, 24), np.float32)
    d[1, 2, 3] = -1
    with pytest.raises(ValueError, match="depths"):
        Scene(cams, _images(6), depths=d)
    with pytest.raises(ValueError, match="bounds upper"):
        Scene(cams, _images(6), bounds=([0, 0, 0], [1, -1, 1]))
    with pytest.raises(TypeError, match=r"cameras\[0\]"):
        Scene(["camera"], _images(1))


def test_degenerate_camera_sets_for_normalisation():
    """Refuse to estimate the region of interest from one, duplicated or colinear cameras."""
    cams = _ring()
    with pytest.raises(ValueError, match="at least 2 cameras, got 1"):
        Scene(cams[:1], _images(1)).normalization()
    with pytest.raises(ValueError, match="coincide"):
        Scene([cams[0], cams[0], cams[0]], _images(3)).normalization()
    line = [Camera.look_at([x, 0, -3], [x, 0, 0], [0, -1, 0], fov_x=0.8, width=24, height=20) for x in (0, 1, 2, 3)]
    with pytest.raises(ValueError, match="one line"):
        Scene(line, _images(4)).normalization()
    # with explicit bounds a single camera is fine
    sim = Scene(cams[:1], _images(1), bounds=([-1, -1, -1], [1, 1, 1])).normalization(margin=0.25)
    np.testing.assert_allclose(sim.to_internal(np.array([[-1, -1, -1], [1, 1, 1.0]])), [[0.25] * 3, [0.75] * 3])
    with pytest.raises(ValueError, match="at least 3 cameras"):
        Scene(cams[:2], _images(2)).require_views(3)


def test_similarity_maps_points_cameras_and_meshes(sphere_scene):
    """Map points, cameras and meshes with a Similarity and back; projections are preserved."""
    sim = Similarity(1e-3, (1e4, -2e4, 3.0))
    x = np.random.default_rng(0).normal(size=(50, 3))
    np.testing.assert_allclose(sim.to_world(sim.to_internal(x)), x, atol=ROUNDTRIP_TOL * 1e4)
    xt = torch.as_tensor(x)
    assert torch.is_tensor(sim.to_internal(xt)) and sim.to_internal(xt).dtype == torch.float64
    np.testing.assert_allclose(sim.to_internal(x), 1e-3 * (x + np.array([1e4, -2e4, 3.0])))
    np.testing.assert_allclose(sim.compose(sim.inverse()).scale, 1.0)
    cam = sphere_scene.cameras[0]
    uv, z = cam.project(x)
    uv2, z2 = sim.to_internal(cam).project(sim.to_internal(x))
    np.testing.assert_allclose(uv2, uv, atol=1e-6)
    np.testing.assert_allclose(z2, 1e-3 * z, rtol=1e-9)
    back = sim.to_world(sim.to_internal(cam))
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-8)
    m = sim.to_internal(sphere_scene.gt_mesh)
    np.testing.assert_allclose(m.vertices, sim.to_internal(sphere_scene.gt_mesh.vertices))
    with pytest.raises(ValueError, match="scale"):
        Similarity(0.0, (0, 0, 0))


@pytest.mark.parametrize("scale, offset", [(1e-3, 1e4), (1e3, 1e4), (1e-3, -1e4)])
def test_normalisation_is_invariant_to_scale_and_offset(sphere_scene, scale, offset):
    """Normalise a scene scaled by 1e-3 / 1e3 and moved by 1e4 to the same internal scene."""
    moved = sphere_scene.transformed(Similarity(scale, (offset, -offset, 0.5 * offset)))
    a, b = sphere_scene.normalized(), moved.normalized()
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_allclose(cb.world_to_camera, ca.world_to_camera, atol=INVARIANCE_TOL)
        np.testing.assert_allclose(cb.K, ca.K)
    torch.testing.assert_close(b.depths, a.depths, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(b.gt_mesh.vertices, a.gt_mesh.vertices, atol=INVARIANCE_TOL)
    # the inverse kept in info maps internal results back to the moved scene's units
    back = b.info["normalization"].to_world(b.gt_mesh.vertices)
    np.testing.assert_allclose(back, moved.gt_mesh.vertices, rtol=1e-9, atol=abs(offset) * scale * 1e-12 + 1e-12)


@pytest.mark.parametrize("source", ["masks", "frusta", "points"])
def test_region_of_interest_contains_the_object(sphere_scene, source):
    """Estimate a region of interest that holds the object, without the ground-truth mesh."""
    s = sphere_scene
    if source == "frusta":
        s = Scene(s.cameras, s.images)
    elif source == "points":
        pts = np.asarray(s.gt_mesh.vertices)
        s = Scene(s.cameras, s.images, points=pts)
    lo, hi = s.region_of_interest()
    v = np.asarray(sphere_scene.gt_mesh.vertices)
    assert np.all(v >= lo - 1e-9) and np.all(v <= hi + 1e-9)
    assert np.max(hi - lo) < 4.0  # the object has extent 2; the estimate must be informative
    m = NORMALIZATION_MARGIN  # the default margin
    nv = s.normalization().to_internal(v)
    assert nv.min() >= m - 1e-9 and nv.max() <= 1 - m + 1e-9


def test_subset_and_downscale(sphere_scene):
    """Select images (split re-indexed) and halve the resolution with matching intrinsics."""
    s = scenes.load("sphere", n_views=6, n_test=2)
    sub = s.subset([7, 0, 2])
    assert len(sub) == 3 and sub.images.shape[0] == 3
    assert sub.train_indices.tolist() == [1, 2] and sub.test_indices.tolist() == [0]
    torch.testing.assert_close(sub.images[0], s.images[7])
    assert len(s.split("test")) == 2
    with pytest.raises(ValueError, match="indices"):
        s.subset([9])
    d = sphere_scene.downscaled(2)
    assert d.images.shape[1:3] == (20, 20) and d.masks.shape == (12, 20, 20)
    p = np.asarray(sphere_scene.gt_mesh.vertices[:20])
    uv, _ = sphere_scene.cameras[0].project(p)
    uv2, _ = d.cameras[0].project(p)
    np.testing.assert_allclose(uv2, uv / 2, atol=1e-9)
    np.testing.assert_allclose(d.images.mean().item(), sphere_scene.images.mean().item(), rtol=1e-5)


def test_save_load_round_trip_bunny(tmp_path):
    """Save the default bunny (small) in Blender format and read it back unchanged."""
    s = scenes.load("bunny", n_views=5, resolution=32, n_test=2)
    s.save(tmp_path / "bunny")
    t = load_scene(tmp_path / "bunny")
    assert len(t) == len(s) and t.name == "bunny" and t.background == s.background
    # loader order: train frames, then test frames; the split indices keep the same order here
    assert t.train_indices.tolist() == list(range(5)) and t.test_indices.tolist() == [5, 6]
    for a, b in zip(s.cameras, t.cameras):
        np.testing.assert_allclose(b.K, a.K, atol=1e-12)
        np.testing.assert_allclose(b.world_to_camera, a.world_to_camera, atol=1e-12)
        assert (b.width, b.height) == (a.width, a.height)
    torch.testing.assert_close(t.images, s.images, rtol=0, atol=PNG_TOL)
    assert torch.equal(t.masks, s.masks)
    np.testing.assert_allclose(t.gt_mesh.vertices, s.gt_mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(t.gt_mesh.faces, s.gt_mesh.faces)


def test_save_load_round_trip_without_masks(tmp_path):
    """Save a scene without masks (a room) so the loader does not invent masks."""
    s = scenes.from_mesh(scenes.load("sphere").gt_mesh, n_views=3, resolution=24, rig="orbit", background="room")
    s.save(tmp_path / "room")
    t = load_scene(tmp_path / "room")
    assert t.masks is None and t.background is None
    torch.testing.assert_close(t.images, s.images, rtol=0, atol=PNG_TOL)


def test_forward_facing_rig_gets_a_region_in_front_of_it():
    """Estimate a region in front of a grid of cameras with parallel axes (LLFF), not an error."""
    from wtopo import Camera, Scene

    cams = []
    for x in (-0.5, 0.0, 0.5):
        for y in (-0.5, 0.0, 0.5):
            w2c = np.eye(4)
            w2c[:3, 3] = [-x, -y, 0.0]  # camera at (x, y, 0) looking along +z (OpenCV axes)
            cams.append(Camera(np.array([[32.0, 0, 32], [0, 32.0, 32], [0, 0, 1]]), w2c, 64, 64))
    sc = Scene(cams, np.zeros((9, 64, 64, 3), np.float32))
    lo, hi = sc.region_of_interest()
    # spread = twice the farthest lateral offset (the corner, sqrt(2) / 2) = sqrt(2), tan(half fov) 1:
    # the focus lies (1 + 2) * sqrt(2) / 2 in front, radius half that; the two carving passes may
    # grow the box by 1.5 cells each (cells of 2 radius / 32 and / 48)
    depth = 1.5 * np.sqrt(2.0)
    radius, growth = 0.5 * depth, 1.5 * depth * (1 / 32 + 1 / 48)
    assert lo[2] > 0.0, "the region must lie in front of the cameras"
    assert np.all(lo <= [0.0, 0.0, depth]) and np.all(hi >= [0.0, 0.0, depth])
    assert depth - radius - growth <= lo[2] and hi[2] <= depth + radius + growth


def test_region_of_interest_holds_a_thin_object():
    """Find a tight region of interest for a masked object a few pixels thick (a coarse grid's cell
    centres miss it; the footprint test must keep it)."""
    import trimesh

    # a cross of two bars 0.06 thick and 1.6 long: about 3 px thick in these 64 px views, while the
    # first carving pass has cells of about 2 x 3.4 / 32 = 0.2, whose centres miss the bars
    bars = [trimesh.creation.box(extents=e) for e in ((1.6, 0.06, 0.06), (0.06, 0.06, 1.6))]
    mesh = trimesh.util.concatenate(bars)
    sc = scenes.from_mesh(mesh, n_views=12, resolution=64, rig="sphere", texture="flat", seed=1)
    thick = 0.06 * sc.cameras[0].K[0, 0] / np.linalg.norm(sc.cameras[0].center)
    assert thick < 4.0, f"the bars should be a few pixels thick, got {thick:.2f} px"
    lo, hi = sc.region_of_interest()
    v = np.asarray(mesh.vertices)
    assert np.all(v >= lo) and np.all(v <= hi), (lo, hi, mesh.bounds)
    # tight: grown by no more than 15 % of the object's extent (1.6) on any side
    assert np.all(mesh.bounds[0] - lo <= 0.24) and np.all(hi - mesh.bounds[1] <= 0.24), (lo, hi)


def test_pixel_directions_at_chosen_pixels_match_the_full_grid():
    """Directions through chosen pixels (a skewed, distorted lens) are the full grid's at those pixels."""
    K = np.array([[50.0, 0.7, 33.0], [0.0, 48.0, 23.0], [0.0, 0.0, 1.0]])
    cam = Camera(K, np.eye(4), 64, 48, np.array([-0.3, 0.05, 0.002, -0.002, 0.0]))
    full = cam.pixel_directions_camera()
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, 48, (40, 5)), rng.integers(0, 64, (40, 5))
    got = cam.pixel_directions_camera(rows, cols)
    assert got.shape == (40, 5, 3)
    np.testing.assert_allclose(got, full[rows, cols], rtol=0, atol=1e-12)  # Newton's stop differs: rounding only
    plain = Camera(K, np.eye(4), 64, 48)  # no lens distortion: the same arithmetic, bit for bit
    np.testing.assert_array_equal(plain.pixel_directions_camera(rows, cols),
                                  plain.pixel_directions_camera()[rows, cols])
    assert cam.pixel_directions_camera(np.zeros(0, int), np.zeros(0, int)).shape == (0, 3)
    with pytest.raises(ValueError, match="rows and cols"):
        cam.pixel_directions_camera(rows)
