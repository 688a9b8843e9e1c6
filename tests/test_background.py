# SPDX-License-Identifier: Apache-2.0
"""Background shells of unmasked captures: where they are seeded (wtopo.fitting.background)."""

import types

import numpy as np
import pytest
import torch

from wtopo.camera import Camera
from wtopo.fitting.background import _COVER_PIXELS, background_surfels, shell_radii, uncovered_pixels

W, H = 40, 30


def _camera():
    return Camera.look_at([0.5, 0.5, 3.0], [0.5, 0.5, 0.5], [0.0, 1.0, 0.0], fov_x=0.8, width=W, height=H)


def _left_half_points(cam, columns):
    """Points on the plane z = 0.5 seen in pixel columns ``< columns``: one per pixel centre of those columns."""
    _, d = cam.pixel_rays("cpu", torch.float64)
    d = d.numpy()[:, :columns].reshape(-1, 3)
    t = (0.5 - cam.center[2]) / d[:, 2]
    return cam.center + t[:, None] * d


def _scene_and_layout(cam):
    images = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(0))
    scene = types.SimpleNamespace(cameras=[cam], images=images)
    layout = types.SimpleNamespace(camera_centers=cam.center[None], roi_center=np.full(3, 0.5), roi_radius=0.5)
    return scene, layout


def test_uncovered_pixels_are_those_farther_than_the_cover_radius_from_every_projected_point(device):
    cam = _camera()
    free = uncovered_pixels([cam], _left_half_points(cam, 10), device)[0]
    assert free.device == torch.device(device)
    free = free.cpu().numpy()
    assert free.shape == (H, W) and free.dtype == bool
    assert not free[:, :10 + _COVER_PIXELS].any()  # the points' columns and their cover radius
    assert free[:, 10 + _COVER_PIXELS:].all()


def test_points_behind_the_camera_or_outside_the_image_cover_nothing():
    cam = _camera()
    behind = 2 * cam.center - _left_half_points(cam, 10)  # mirrored through the camera centre: z < 0
    outside = np.array([[50.0, 0.5, 0.5], [0.5, -40.0, 0.5]])
    free = uncovered_pixels([cam], np.concatenate([behind, outside]))[0]
    assert bool(free.all())


def test_shells_are_seeded_only_on_pixels_the_points_leave_free(device):
    cam = _camera()
    scene, layout = _scene_and_layout(cam)
    pts = _left_half_points(cam, 20)
    s = background_surfels(scene, layout, 400, sh_degree=0, opacity=0.3, device=torch.device(device),
                           generator=torch.Generator().manual_seed(1), covered_by=pts)
    means = s.means.detach().double().cpu().numpy()
    uv, z = cam.project(means)
    assert (z > 0).all()
    col = np.floor(uv[:, 0]).astype(int)
    assert (col >= 20 + _COVER_PIXELS).all() and (col < W).all(), col.min()
    r = np.linalg.norm(means - layout.roi_center, axis=1)
    assert np.allclose(np.sort(np.unique(np.round(r, 4))), np.round(shell_radii(layout), 4), rtol=1e-4)
    # the colour of the pixel each seed came from
    row = np.floor(uv[:, 1]).astype(int)
    want = scene.images[0].numpy()[row, col]
    assert np.allclose(s.colors().cpu().numpy(), want, atol=1e-5)


@pytest.mark.parametrize("covered", ["none", "everything", "empty"])
def test_without_free_pixels_or_points_every_pixel_may_seed(covered):
    cam = _camera()
    scene, layout = _scene_and_layout(cam)
    pts = {"none": None, "everything": _left_half_points(cam, W), "empty": np.zeros((0, 3))}[covered]
    s = background_surfels(scene, layout, 2000, sh_degree=0, opacity=0.3, device=torch.device("cpu"),
                           generator=torch.Generator().manual_seed(2), covered_by=pts)
    uv, _ = cam.project(s.means.detach().double().numpy())
    col = np.floor(uv[:, 0]).astype(int)
    assert len(s) == 2000 and col.min() < 3 and col.max() > W - 4  # seeds across the whole image


def test_no_background_surfels_asked_gives_none():
    cam = _camera()
    scene, layout = _scene_and_layout(cam)
    assert background_surfels(scene, layout, 0, sh_degree=0, opacity=0.3, device=torch.device("cpu"),
                              generator=torch.Generator()) is None


def test_unseen_shells_are_pruned_and_seen_or_inner_surfels_stay():
    """A camera at z = 3 looks down -z at four opaque layers at z = 0.5 ... 0.35 inside the region of interest;
    behind them a small shell outside the region (hidden), another beside the layers' opaque core (seen), and a
    small inner surfel behind them (hidden, but inside). Their view directions come from a real render's
    visibility: only the hidden shell goes."""
    from wtopo.fitting import densify as dens
    from wtopo.fitting.background import BackgroundState, prune_background
    from wtopo.fitting.surfels import Surfels
    from wtopo.rasterize import rasterize_surfels

    cam = Camera.look_at([0.5, 0.5, 3.0], [0.5, 0.5, 0.5], [0.0, 1.0, 0.0], fov_x=0.8, width=W, height=H)
    layers = [[0.5, 0.5, z] for z in (0.5, 0.45, 0.4, 0.35)]
    pts = torch.tensor(layers + [[0.5, 0.5, -4.0],    # a shell straight behind them, outside the region: hidden
                                 [-1.5, 0.5, -4.0],   # a shell 14 px beside their core: seen
                                 [0.5, 0.5, 0.2]])    # inside the region, behind them: hidden but kept
    n = len(pts)
    cols = torch.rand(n, 3, generator=torch.Generator().manual_seed(3))
    nrm = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3)
    scale = torch.tensor([0.3] * 4 + [0.05, 0.3, 0.02])
    s = Surfels.from_points(pts, cols, scales=scale, normals=nrm, opacity=0.99)
    out = rasterize_surfels(s.means, s.quats, s.scales, s.opacities, s.sh, cam)
    visible = out.visibility > 0
    assert visible.tolist() == [True] * 4 + [False, True, False], out.visibility
    dens.accumulate_view_directions(s, torch.as_tensor(cam.center, dtype=torch.float32), visible)
    layout = types.SimpleNamespace(roi_center=np.full(3, 0.5), roi_radius=0.5, roi_lower=np.zeros(3),
                                   roi_upper=np.ones(3), camera_centers=cam.center[None], near=0.1)
    state = BackgroundState(layout, torch.device("cpu"))
    assert state.outside_roi(s.means).tolist() == [False] * 4 + [True, True, False]
    # and one on the lens, just behind the camera: unseen and outside too, but counted once, as near the camera
    s.append(*Surfels.from_points(torch.tensor([[0.5, 0.5, 3.05]]), cols[:1], scales=torch.tensor([0.01]),
                                  normals=nrm[:1], opacity=0.99).take(slice(None)))
    assert prune_background(s, state) == (1, 0)  # without unseen: the lens only
    s.append(*Surfels.from_points(torch.tensor([[0.5, 0.5, 3.05]]), cols[:1], scales=torch.tensor([0.01]),
                                  normals=nrm[:1], opacity=0.99).take(slice(None)))
    assert prune_background(s, state, unseen=True) == (1, 1)  # one prune for both
    assert torch.allclose(s.means.detach(), pts[[0, 1, 2, 3, 5, 6]])
    assert prune_background(s, state, unseen=True) == (0, 0)  # nothing left to prune


def test_unseen_prune_never_removes_every_surfel():
    from wtopo.fitting.background import BackgroundState, prune_background
    from wtopo.fitting.surfels import Surfels

    s = Surfels.from_points(torch.tensor([[5.0, 0.0, 0.0], [0.0, 6.0, 0.0]]), torch.full((2, 3), 0.5),
                            scales=torch.tensor([0.1, 0.1]))
    layout = types.SimpleNamespace(roi_center=np.zeros(3), roi_radius=0.5, roi_lower=-np.ones(3) / 2,
                                   roi_upper=np.ones(3) / 2, camera_centers=np.array([[0.0, 0.0, 3.0]]), near=0.1)
    assert prune_background(s, BackgroundState(layout, torch.device("cpu")), unseen=True) == (0, 0) and len(s) == 2
