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
                           generator=torch.Generator().manual_seed(1), free=uncovered_pixels([cam], pts, device))
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
    free = None if pts is None else uncovered_pixels([cam], pts)
    s = background_surfels(scene, layout, 2000, sh_degree=0, opacity=0.3, device=torch.device("cpu"),
                           generator=torch.Generator().manual_seed(2), free=free)
    uv, _ = cam.project(s.means.detach().double().numpy())
    col = np.floor(uv[:, 0]).astype(int)
    assert len(s) == 2000 and col.min() < 3 and col.max() > W - 4  # seeds across the whole image


def test_no_background_surfels_asked_gives_none():
    cam = _camera()
    scene, layout = _scene_and_layout(cam)
    assert background_surfels(scene, layout, 0, sh_degree=0, opacity=0.3, device=torch.device("cpu"),
                              generator=torch.Generator()) is None


def test_surfels_on_a_lens_are_pruned_and_the_rest_stay():
    """A camera at z = 3 with near distance 0.1: a surfel 0.05 behind its centre goes, one 0.2 in front of it, one
    inside the region and one far outside it stay; a set of surfels all on the lens is left whole."""
    from wtopo.fitting.background import BackgroundState, prune_near_cameras
    from wtopo.fitting.surfels import Surfels

    pts = torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 3.05], [0.5, 0.5, 2.8], [-4.0, 0.5, -4.0]])
    s = Surfels.from_points(pts, torch.full((4, 3), 0.5), scales=torch.full((4,), 0.01))
    layout = types.SimpleNamespace(roi_center=np.full(3, 0.5), roi_radius=0.5, roi_lower=np.zeros(3),
                                   roi_upper=np.ones(3), camera_centers=np.array([[0.5, 0.5, 3.0]]), near=0.1)
    state = BackgroundState(layout, torch.device("cpu"))
    assert state.near_cameras(s.means).tolist() == [False, True, False, False]
    assert prune_near_cameras(s, state) == 1
    assert torch.equal(s.means.detach(), pts[[0, 2, 3]])
    assert prune_near_cameras(s, state) == 0  # nothing left on the lens
    lens = Surfels.from_points(pts[[1, 1]], torch.full((2, 3), 0.5), scales=torch.full((2,), 0.01))
    assert prune_near_cameras(lens, state) == 0 and len(lens) == 2  # never every surfel


def _half_flat_image(flat_side: str) -> torch.Tensor:
    """[H, W, 3]: one half (``"left"`` or ``"right"``, 20 columns) flat grey, the other random texture."""
    img = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(4))
    cols = slice(0, W // 2) if flat_side == "left" else slice(W // 2, W)
    img[:, cols] = 0.6
    return img


def test_untextured_windows_are_the_sweeps_flat_ones():
    from wtopo.geometry.mvs import untextured

    assert bool(untextured(torch.full((H, W, 3), 0.3)).all())
    assert not bool(untextured(torch.rand(H, W, 3, generator=torch.Generator().manual_seed(5))).any())
    flat = untextured(_half_flat_image("left"))
    assert bool(flat[:, :W // 2 - 3].all())  # windows (7 px) wholly in the flat half
    assert not bool(flat[:, W // 2:].any())


@pytest.mark.parametrize("free_side,wanted", [("left", False), ("right", True)])
def test_shells_are_wanted_only_where_the_unexplained_pixels_hold_texture(free_side, wanted):
    """The left half is flat: unexplained pixels there (windows wholly flat but for 3 columns) call for no shells;
    unexplained textured pixels do."""
    from wtopo.fitting.background import UNTEXTURED_SHARE, shells_wanted

    img = _half_flat_image("left")
    free = torch.zeros(H, W, dtype=torch.bool)
    free[:, :W // 2] = free_side == "left"
    free[:, W // 2:] = free_side == "right"
    got, share = shells_wanted(img[None], [free])
    want_share = (W // 2 - 3) / (W // 2) if free_side == "left" else 0.0
    assert got == wanted and share == pytest.approx(want_share)
    assert (share <= UNTEXTURED_SHARE) == wanted
    assert shells_wanted(img[None], [torch.zeros(H, W, dtype=torch.bool)]) == (False, None)  # nothing unexplained


def _initial_surfels(monkeypatch, flat_side: str, forced: bool = False):
    """scene_surfels on one view whose left half the stereo explains (a stand-in for its points), the
    ``flat_side`` half flat: ``(surfels, [(event, fields)])``, 200 stereo surfels and up to 300 shells."""
    from wtopo.fitting import _init_surfels
    from wtopo.fitting.config import FitConfig, InitSource
    from wtopo.geometry.mvs import MVSPoints

    cam = _camera()
    pts = _left_half_points(cam, W // 2)
    monkeypatch.setattr(_init_surfels, "stereo_points",
                        lambda *a: MVSPoints(pts, np.full_like(pts, 0.5), np.tile([0.0, 0.0, 1.0], (len(pts), 1)), 0.5))
    scene = types.SimpleNamespace(cameras=[cam], images=_half_flat_image(flat_side)[None], points=None)
    layout = types.SimpleNamespace(camera_centers=cam.center[None], roi_center=np.full(3, 0.5), roi_radius=0.5,
                                   roi_lower=np.zeros(3), roi_upper=np.ones(3), near=0.01)
    cfg = FitConfig()
    cfg.init.source, cfg.init.num_points, cfg.init.background_points, cfg.sh_degree = InitSource.MVS, 200, 300, 0
    events = []
    s = _init_surfels.scene_surfels(scene, cfg, layout, torch.device("cpu"), torch.Generator().manual_seed(0), None,
                                    lambda name, **kw: events.append((name, kw)), forced=forced)
    return s, events


@pytest.mark.parametrize("flat_side,seeded", [("right", 0), ("left", 300)])
def test_a_fit_seeds_shells_only_when_the_stereo_left_texture_unexplained(monkeypatch, flat_side, seeded):
    """A flat right half (unexplained) gets no shells, a textured one gets them all; either way the event says how
    many and the untextured share."""
    s, events = _initial_surfels(monkeypatch, flat_side)
    assert len(s) == 200 + seeded
    (name, kw), = events
    assert name == "background_shells" and kw["seeded"] == seeded and kw["lens_pruned"] == 0
    assert (kw["untextured_share"] > 0.5) == (seeded == 0)


def test_set_shells_stand_whatever_the_texture(monkeypatch):
    """init.background_points set in the configuration: the flat case above seeds its shells all the same."""
    s, events = _initial_surfels(monkeypatch, "right", forced=True)
    (_, kw), = events
    assert len(s) == 500 and kw["seeded"] == 300 and kw["untextured_share"] > 0.5


def test_the_plan_says_when_the_fit_seeded_no_shells():
    """revise_plan: a scene's plan of shells becomes none, with the share as the reason; seeded shells (or no
    event) leave the plan as it was."""
    import trimesh

    from wtopo import Scene, scenes
    from wtopo.fitting._init_surfels import revise_plan
    from wtopo.fitting.config import FitConfig
    from wtopo.fitting.plan import make_plan

    lit = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24, rig="sphere",
                           texture="coffee", name="open")
    plan = make_plan(Scene(cameras=lit.cameras, images=lit.images, name="open").normalized(), FitConfig(),
                     torch.device("cpu"))
    assert plan.background_points > 0
    assert revise_plan(plan, []) is plan
    assert revise_plan(plan, [{"event": "background_shells", "seeded": 7, "untextured_share": 0.1}]) is plan
    got = revise_plan(plan, [{"event": "densify"}, {"event": "background_shells", "seeded": 0,
                                                    "untextured_share": 0.879}])
    assert got.background_points == 0 and "88% of the pixels" in got.reasons["background_points"]
    assert got.to_dict()["background_points"]["value"] == 0 and "no shells" in str(got)
    assert got.sh_degree == plan.sh_degree and got.layout is plan.layout
    none_left = revise_plan(plan, [{"event": "background_shells", "seeded": 0, "untextured_share": None}])
    assert "no pixel unexplained" in none_left.reasons["background_points"]
