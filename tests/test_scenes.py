# SPDX-License-Identifier: Apache-2.0
"""Synthetic scenes: rendered depth / normals / masks against an analytic sphere, rigs, determinism."""

import math

import numpy as np
import pytest
import torch
import trimesh

from wtopo import metrics, scenes

# A level-3 icosphere of radius 1 lies within 1 - cos(half its ~0.16 rad edge angle) ~ 4e-3 of the
# unit sphere; ray depths differ from the analytic sphere by at most that over the grazing factor
# away from the silhouette (checked on rays whose analytic hit is at least 0.3 rad from grazing).
DEPTH_TOL = 2e-2
NORMAL_COS_MIN = 0.98  # face normal vs radial direction: cos of half the icosphere's edge angle
MASK_MISMATCH_MAX = 0.03  # pixels whose centre straddles the polyhedral silhouette


@pytest.fixture(scope="module")
def sphere_scene():
    return scenes.load("sphere")


def test_sphere_scene_matches_analytic_sphere(sphere_scene):
    """Check depth, normals and masks of the icosphere scene against the unit sphere."""
    s = sphere_scene
    assert s.images.shape == (12, 40, 40, 3) and s.masks.dtype == torch.bool
    assert s.background == (0.0, 0.0, 0.0) and s.gt_mesh is not None
    total = 0
    for i, cam in enumerate(s.cameras):
        o, d = (x.numpy() for x in cam.pixel_rays("cpu", torch.float64))
        # |o + t d|^2 = 1
        a, b, c = (d * d).sum(-1), 2 * (o * d).sum(-1), (o * o).sum(-1) - 1
        disc = b * b - 4 * a * c
        hit = disc > 0
        t = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0)
        m = s.masks[i].numpy()
        assert np.mean(m != hit) < MASK_MISMATCH_MAX
        p = o + t[..., None] * d
        cos_graze = np.abs((p * d).sum(-1)) / np.linalg.norm(d, axis=-1)
        inner = hit & m & (cos_graze > math.sin(0.3))
        total += inner.sum()
        np.testing.assert_allclose(s.depths[i].numpy()[inner], t[inner], atol=DEPTH_TOL)
        n = s.normals[i].numpy()[m]
        np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
        assert np.all((n * d[m]).sum(-1) < 0)  # facing the camera
        radial = p[inner] / np.linalg.norm(p[inner], axis=-1, keepdims=True)
        assert np.all((s.normals[i].numpy()[inner] * radial).sum(-1) > NORMAL_COS_MIN)
        assert np.all(s.depths[i].numpy()[~m] == 0) and np.all(s.images[i].numpy()[~m] == 0)
    assert total > 12 * 200  # the comparison covered many pixels


def test_deterministic_given_seed():
    """Render identical scenes for one seed and different ones for another."""
    m = trimesh.creation.icosphere(2)
    a = scenes.from_mesh(m, n_views=4, resolution=24, seed=3)
    b = scenes.from_mesh(m, n_views=4, resolution=24, seed=3)
    c = scenes.from_mesh(m, n_views=4, resolution=24, seed=4)
    assert torch.equal(a.images, b.images)
    assert not torch.equal(a.images, c.images)


@pytest.mark.parametrize("rig", scenes.RIGS)
def test_rigs(rig):
    """Place each rig's cameras as documented around the bounding sphere."""
    up = np.array([0.0, 1.0, 0.0])
    cams = scenes.rig_cameras(rig, 9, [1.0, 2.0, 3.0], 0.5, resolution=(32, 24), up=up, seed=1)
    assert len(cams) == 9 and all((c.width, c.height) == (32, 24) for c in cams)
    centers = np.stack([c.center for c in cams]) - [1.0, 2.0, 3.0]
    fwd = np.stack([c.forward for c in cams])
    if rig == "forward":
        np.testing.assert_allclose(fwd, np.broadcast_to(fwd[0], fwd.shape), atol=1e-12)  # parallel axes
    else:
        to_center = -centers / np.linalg.norm(centers, axis=1, keepdims=True)
        np.testing.assert_allclose(fwd, to_center, atol=1e-9)
        dist = np.linalg.norm(centers, axis=1)
        np.testing.assert_allclose(dist, dist[0], rtol=1e-9)
        # the bounding sphere fits inside the narrower field of view
        half = math.atan(0.5 * cams[0].height / cams[0].K[1, 1])
        assert math.asin(0.5 / dist[0]) < half
    elev = centers @ up
    if rig == "hemisphere":
        assert np.all(elev > 0)
    elif rig == "orbit":
        np.testing.assert_allclose(elev, elev[0], atol=1e-9)
    elif rig == "sphere":
        assert elev.min() < 0 < elev.max()
    with pytest.raises(ValueError, match="rig"):
        scenes.rig_cameras("spiral", 4, [0, 0, 0], 1.0, resolution=16)


@pytest.mark.parametrize("background", ["room", "ground"])
def test_room_background(background):
    """Add floor (and walls) as extra geometry: no masks, gt mesh = object only, textured background."""
    m = trimesh.creation.icosphere(2)
    s = scenes.from_mesh(m, n_views=4, resolution=32, rig="hemisphere", background=background, mapping="spherical")
    assert s.masks is None and s.background is None
    assert len(s.gt_mesh.faces) == len(m.faces)
    assert (s.depths > 0).float().mean() > 0.6  # the scenery fills most of the frame
    lit = s.images[s.depths > 0]
    assert lit.std(0).min() > 0.02  # textured, not a constant colour
    with pytest.raises(ValueError, match="hemisphere"):
        scenes.from_mesh(m, n_views=4, resolution=16, rig="sphere", background=background)


def test_argument_errors():
    """Reject unknown textures, backgrounds, mappings and empty meshes."""
    m = trimesh.creation.icosphere(1)
    with pytest.raises(ValueError, match="texture"):
        scenes.from_mesh(m, n_views=2, resolution=8, texture="nope")
    with pytest.raises(ValueError, match="background"):
        scenes.from_mesh(m, n_views=2, resolution=8, background="grey")
    with pytest.raises(ValueError, match="mapping"):
        scenes.from_mesh(m, n_views=2, resolution=8, mapping="cubic")
    with pytest.raises(ValueError, match="faces"):
        scenes.from_mesh((np.zeros((3, 3)), np.zeros((0, 3), int)), n_views=2, resolution=8)
    with pytest.raises(ValueError, match="name"):
        scenes.load("teapot")


def test_bunny_defaults():
    """Load the default bunny: 32 views of 128 px with masks, watertight gt mesh in the USD frame."""
    s = scenes.load("bunny")
    assert s.images.shape == (32, 128, 128, 3) and s.masks is not None and s.background == (0.0, 0.0, 0.0)
    st = metrics.mesh_stats(s.gt_mesh)
    assert st["watertight"] and st["n_faces"] > 10_000
    mesh, up = scenes.bunny_mesh()
    np.testing.assert_array_equal(s.gt_mesh.vertices, mesh.vertices)
    assert up == (0.0, 1.0, 0.0)
    cover = s.masks.float().mean((1, 2))
    assert cover.min() > 0.05  # the bunny is visible in every view
    lo, hi = s.region_of_interest()
    assert np.all(mesh.vertices >= lo) and np.all(mesh.vertices <= hi)


# -- unbounded environment -------------------------------------------------------------------------
TINY_ENV = dict(n_views=6, resolution=(48, 36), n_test=2)  # a tiny unbounded scene: seconds to render


@pytest.fixture(scope="module")
def env_scene():
    return scenes.load("bunny_env", **TINY_ENV)


def test_environment_scene(env_scene):
    """Render the environment: no masks, sky with depth 0, ground and hills in gt_mesh, roi recorded."""
    s = env_scene
    assert s.masks is None and s.background is None and s.bounds is None
    assert s.images.shape == (8, 36, 48, 3) and list(s.test_indices) == [6, 7]
    bunny, up = scenes.bunny_mesh()
    assert len(s.gt_mesh.faces) > len(bunny.faces)  # ground and hills are ground truth too
    sky = s.depths == 0
    assert 0.02 < sky.float().mean() < 0.6  # sky visible above the horizon, scenery below
    assert torch.all(s.normals[sky] == 0)
    assert s.images[sky].std(0).min() > 0.01  # gradient and clouds, not a constant
    assert s.images[sky][:, 2].mean() > s.images[sky][:, 0].mean()  # bluish
    lo, hi = (np.asarray(b) for b in s.info["roi"])
    assert np.all(bunny.vertices >= lo) and np.all(bunny.vertices <= hi)
    floor = bunny.vertices[:, 1].min()
    assert lo[1] < floor < hi[1]  # the ground belongs to the region of interest
    ext = np.asarray(s.gt_mesh.bounds)
    assert np.all(ext[1] - ext[0] > 10 * (hi - lo)[[0, 2]].max() * np.array([1, 0, 1]))  # far beyond the roi
    centers = np.stack([c.center for c in s.cameras])
    assert np.all(centers[:, 1] > floor)  # cameras above the ground
    span = np.concatenate([centers, [lo, hi]])
    extent = np.linalg.norm(span.max(0) - span.min(0))
    # the ground truth itself keeps the criterion: no surface within 5 % of the extent of a camera
    assert metrics.camera_clearance(s.gt_mesh, centers).min() > 0.05 * extent
    b = scenes.load("bunny_env", bounds_from_roi=True, **TINY_ENV)
    np.testing.assert_array_equal(b.bounds[0], lo)
    np.testing.assert_array_equal(b.bounds[1], hi)


def test_environment_forward_rig():
    """Place the forward-facing rig above the ground with parallel axes and sky behind the object."""
    s = scenes.load("bunny_env_forward", **TINY_ENV)
    floor = scenes.bunny_mesh()[0].vertices[:, 1].min()
    assert all(c.center[1] > floor for c in s.cameras)
    fwd = np.stack([c.forward for c in s.cameras])
    np.testing.assert_allclose(fwd, np.broadcast_to(fwd[0], fwd.shape), atol=1e-12)
    assert (s.depths == 0).float().mean() > 0.02


def test_environment_photometric_and_seed(env_scene):
    """Apply per-image gains to training views only, deterministically per seed."""
    clean = scenes.load("bunny_env", photometric=None, **TINY_ENV)
    gains = np.asarray(env_scene.info["gains"])
    assert gains.shape == (6, 3) and np.ptp(gains[:, 0]) > 0.02  # exposure varies between images
    assert np.all(np.abs(gains - 1) <= 0.1 * 1.03 + 0.03 + 1e-9)
    torch.testing.assert_close(env_scene.images[6:], clean.images[6:], rtol=0, atol=0)  # held-out views clean
    # the noisy image is gain * clean + noise: its residual after the gain is the 1 % noise
    for i in range(6):
        a, c = env_scene.images[i].numpy(), clean.images[i].numpy()
        ok = (a > 0.05) & (a < 0.95) & (c * gains[i] < 0.95)  # away from clipping
        r = a[ok] - (c * gains[i])[ok]
        assert abs(r.mean()) < 3e-3 and 0.007 < r.std() < 0.013
    again = scenes.load("bunny_env", **TINY_ENV)
    torch.testing.assert_close(again.images, env_scene.images, rtol=0, atol=0)
    other = scenes.load("bunny_env", seed=1, **TINY_ENV)
    assert not torch.equal(other.images, env_scene.images)
    with pytest.raises(ValueError, match="Photometric.noise"):
        scenes.Photometric(noise=-0.1)
    with pytest.raises(TypeError, match="photometric"):
        scenes.load("bunny_env", photometric=0.01, **TINY_ENV)
    with pytest.raises(ValueError, match="bounds_from_roi"):
        scenes.from_mesh(trimesh.creation.icosphere(1), n_views=2, resolution=8, bounds_from_roi=True)


def test_forward_rig_region_sits_at_the_depth_the_pictures_show():
    """A forward-facing rig without bounds, masks or points: the region of interest is centred at the
    depth stereo measures in the middle of the pictures (the object), not at the rig-geometry guess,
    and holds the object's nearest point; a capture without texture falls back to the guess."""
    from wtopo import Scene
    from wtopo.geometry.region import visual_hull_box

    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    s = scenes.from_mesh(ball, n_views=9, resolution=(64, 48), rig="forward", background="black", n_test=0)
    sc = Scene(s.cameras, s.images)  # no masks: the fit would treat it as a scene
    lo, hi = sc.region_of_interest()
    fwd = s.cameras[0].forward
    nearest = -fwd  # the point of the unit ball nearest the rig
    assert np.all(lo <= nearest) and np.all(hi >= nearest)
    guess = visual_hull_box(s.cameras, None)  # the cameras alone
    origin = np.mean([c.center for c in s.cameras], axis=0)
    depth = float((0.5 * (lo + hi) - origin) @ fwd)
    truth = float(-origin @ fwd)  # the ball's centre
    guessed = float((0.5 * (guess[0] + guess[1]) - origin) @ fwd)
    assert abs(depth - truth) < 1.0, (depth, truth)  # within the ball's radius
    assert abs(guessed - truth) > abs(depth - truth)
    flat = Scene(s.cameras, torch.full_like(s.images, 0.5))
    np.testing.assert_allclose(np.stack(flat.region_of_interest()), np.stack(guess))
