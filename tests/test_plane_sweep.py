# SPDX-License-Identifier: Apache-2.0
"""The plane sweep's score (``kernels/plane_sweep.py`` through :func:`wtopo.plane_sweep.plane_costs`): the torch
formulation it replaced in float64 (both plane families, pinhole and barrel lens, one to three sources), the true
plane winning on an analytic scene, and the stiff cases (sources behind the camera, depths not positive or out
of range, untextured sources, a one-pixel window, an image smaller than the window, chunk and thread splits)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lenses import barrel_twin
from reference.plane_sweep import plane_costs_torch, window_moments
from shapes import plane_truth, textured_plane

from wtopo.camera import Camera
from wtopo.geometry.mvs import gray
from wtopo.multiview_ncc import source_params
from wtopo.plane_sweep import LevelPlanes, SweepReference, plane_costs

HALF = 3
MIN_TEXTURE = 1e-4
# float32 window sums of 49 terms against float64 running sums: observed <= 6e-5 on the textured plane; the NCC's
# denominator is at least sqrt(MIN_TEXTURE var_r), so the comparison is held where the reference window is
# textured (var_r > 1e-3: the sweep drops pixels under 1e-4) and away from the thresholds a round-off can flip
COST_ATOL = 1e-3
UP = torch.tensor([0.0, 0.0, 1.0])  # the textured plane's normal


@pytest.fixture(scope="module")
def plane():
    return textured_plane()


def _inputs(cams, imgs, ref=0, srcs=(1, 2), device="cpu"):
    g = gray(torch.as_tensor(imgs[ref]).float())
    mu, var = window_moments(g, HALF)
    o, d = cams[ref].pixel_rays()
    reference = SweepReference(g, mu, var, d.float().contiguous())
    sources = torch.stack([gray(torch.as_tensor(imgs[j]).float()) for j in srcs])
    params = torch.stack([source_params(cams[ref], cams[j]) for j in srcs])
    to = lambda t: t.to(device)  # noqa: E731
    return SweepReference(*map(to, reference)), to(sources), to(params), o.float()


def _fronto(cam, n=40):
    z = float(np.linalg.norm(cam.center))
    return torch.linspace(1 / (0.5 * z), 1 / (2 * z), n)


def _level(cam, o, d, n=31, device="cpu"):
    z = float(np.linalg.norm(cam.center))
    return LevelPlanes(torch.linspace(-0.3, 0.3, n).to(device), (o * UP).sum(-1).to(device),
                       (d * UP).sum(-1).to(device), 0.5 * z, 2 * z)


def _reference(reference, sources, params, planes, best):
    f = lambda t: t.detach().cpu().double()  # noqa: E731
    kw = dict(half=HALF, best=best, min_texture=MIN_TEXTURE, details=True)
    if isinstance(planes, LevelPlanes):
        return plane_costs_torch(*map(f, reference), f(sources), f(params), f(planes.heights),
                                 level=(f(planes.camera_height), f(planes.rate), planes.lo, planes.hi), **kw)
    return plane_costs_torch(*map(f, reference), f(sources), f(params), f(planes), **kw)


@pytest.mark.parametrize("lens", ["pinhole", "barrel"])
@pytest.mark.parametrize("family", ["fronto", "level"])
@pytest.mark.parametrize("srcs,best", [((1, 2), 1), ((1, 2, 3), 2), ((2,), 1)])
def test_costs_match_the_torch_reference(plane, device, lens, family, srcs, best):
    cams, imgs = (plane.cameras, plane.images) if lens == "pinhole" else barrel_twin(plane)
    reference, sources, params, o = _inputs(cams, imgs, srcs=srcs, device=device)
    planes = (_fronto(cams[0]).to(device) if family == "fronto"
              else _level(cams[0], o, reference.dirs.cpu(), device=device))
    cost = plane_costs(reference, sources, params, planes, half=HALF, best=best, min_texture=MIN_TEXTURE).cpu()
    want, det = _reference(reference, sources, params, planes, best)
    W, H = cams[0].width, cams[0].height
    fragile = (((det["var_s"] - MIN_TEXTURE).abs() < 1e-6) | (det["u"].abs() < 1e-3) | ((det["u"] - W).abs() < 1e-3)
               | (det["v"].abs() < 1e-3) | ((det["v"] - H).abs() < 1e-3) | (det["z"].abs() < 1e-6)).any(1)
    held = ~fragile & (reference.var.cpu() > 1e-3)
    assert float(held.double().mean()) > 0.2 and float((want[held] > 0.5).double().mean()) > 0.02, "not exercised"
    torch.testing.assert_close(cost.double()[held], want[held], atol=COST_ATOL, rtol=0)
    assert bool(torch.isfinite(cost).all()) and float(cost.min()) >= -1 and float(cost.max()) <= 1 + 1e-4


def test_level_plane_at_the_true_height_wins(plane):
    """The quad is the level plane at height 0: it wins where the views see it, within one plane step."""
    cams = plane.cameras
    reference, sources, params, o = _inputs(cams, plane.images, srcs=(1, 2, 3))
    planes = _level(cams[0], o, reference.dirs, n=31)  # height 0 is plane 15, 0.02 apart
    cost = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=MIN_TEXTURE)
    _, _, alpha = plane_truth(cams[0])
    seen = (alpha > 0) & (reference.var > 1e-3) & (cost[15] > 0.5)
    assert float(seen.double().mean()) > 0.2
    assert float(cost[15][seen].median()) > 0.8
    assert float(((cost.argmax(0) - 15).abs() <= 1)[seen].double().mean()) > 0.95


def test_fronto_planes_find_the_depth(plane):
    """Planes facing the camera: the winner's inverse depth lies within two plane steps of the quad's at most
    textured pixels (a slanted surface is not one fronto plane across the window, so not always the nearest)."""
    cams = plane.cameras
    reference, sources, params, _ = _inputs(cams, plane.images, srcs=(1, 2, 3))
    planes = _fronto(cams[0], n=96)
    cost = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=MIN_TEXTURE)
    depth, _, alpha = plane_truth(cams[0])
    seen = (alpha > 0) & (reference.var > 1e-3) & (cost.max(0).values > 0.5)
    step = float(planes[0] - planes[1])
    err = (planes[cost.argmax(0)] - 1 / depth.clamp_min(1e-6)).abs() / step
    assert float(seen.double().mean()) > 0.1
    assert float((err <= 2)[seen].double().mean()) > 0.9


def test_sources_behind_and_bad_depths_score_minus_one(plane):
    cams = plane.cameras
    reference, sources, params, o = _inputs(cams, plane.images, srcs=(1,))
    # the source turned around: every point the reference sees lies behind it
    c = cams[1]
    flip = np.diag([-1.0, 1.0, -1.0])
    behind = Camera(c.K, np.block([[flip @ c.R, (flip @ c.t)[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]),
                    c.width, c.height)
    back = torch.stack([source_params(cams[0], behind)])
    assert bool((plane_costs(reference, sources, back, _fronto(cams[0]), half=HALF, best=1,
                             min_texture=MIN_TEXTURE) == -1).all())
    # inverse depths 0 (infinitely far) and negative (behind the reference), in with good ones
    planes = torch.cat([torch.tensor([0.0, -0.5]), _fronto(cams[0])])
    cost = plane_costs(reference, sources, params, planes, half=HALF, best=1, min_texture=MIN_TEXTURE)
    assert bool((cost[:2] == -1).all()) and float((cost[2:].max(0).values > 0.5).double().mean()) > 0.05
    # level planes whose depths all fall outside [lo, hi]
    lv = _level(cams[0], o, reference.dirs)
    lv = lv._replace(lo=100.0, hi=200.0)
    assert bool((plane_costs(reference, sources, params, lv, half=HALF, best=1, min_texture=MIN_TEXTURE) == -1).all())


def test_untextured_sources_and_one_pixel_windows_score_minus_one(plane):
    """A flat grey source is textured only where a window reaches past its border (zero padding)."""
    cams = plane.cameras
    reference, sources, params, _ = _inputs(cams, plane.images, srcs=(1, 2))
    flat = torch.full_like(sources, 0.5)
    planes = _fronto(cams[0])
    cost = plane_costs(reference, flat, params, planes, half=HALF, best=1, min_texture=MIN_TEXTURE)
    want, det = _reference(reference, flat, params, planes, 1)
    inside = (det["var_s"] == 0).all(1)  # every tap of both sources' windows inside them
    assert float(inside.double().mean()) > 0.3 and bool((cost[inside] == -1).all())
    assert bool((plane_costs(reference, sources, params, planes, half=0, best=2, min_texture=MIN_TEXTURE) == -1).all())


def test_image_smaller_than_the_window_matches_the_reference(device):
    """A 3 x 2 view under a 7 x 7 window: every window is clipped on every side."""
    rng = np.random.default_rng(0)
    K = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.0], [0.0, 0.0, 1.0]])

    def cam(x):
        E = np.eye(4)
        E[0, 3] = -x
        E[2, 3] = 2.0
        return Camera(K, E, 3, 2)

    cams = [cam(0.0), cam(0.3), cam(-0.3)]
    imgs = torch.as_tensor(rng.random((3, 2, 3, 3)), dtype=torch.float32)
    reference, sources, params, _ = _inputs(cams, imgs, srcs=(1, 2), device=device)
    planes = torch.linspace(1 / 1.0, 1 / 4.0, 16).to(device)
    cost = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=0.0).cpu()
    want, det = _reference(reference, sources, params, planes, 2)
    held = ~((det["var_s"].abs() < 1e-6) | (det["u"].abs() < 1e-3) | ((det["u"] - 3).abs() < 1e-3)
             | (det["v"].abs() < 1e-3) | ((det["v"] - 2).abs() < 1e-3)).any(1)
    assert float((want[held] > -1).double().mean()) > 0.3, "not exercised"
    torch.testing.assert_close(cost.double()[held], want[held], atol=COST_ATOL, rtol=0)


def test_chunks_strips_and_cpu_threads_give_the_same_costs(plane, monkeypatch):
    """Chunks of planes, CPU threads and strips change nothing; one pixel a thread (CUDA's layout: direct float32
    sums instead of float64 sliding ones) agrees within float32 round-off (observed 2.6e-5)."""
    import wtopo.plane_sweep as ps

    cams = plane.cameras
    reference, sources, params, o = _inputs(cams, plane.images, srcs=(1, 2, 3))
    planes = _level(cams[0], o, reference.dirs)
    monkeypatch.setenv("WTOPO_NUM_THREADS", "1")
    one = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=MIN_TEXTURE)
    monkeypatch.setenv("WTOPO_NUM_THREADS", "3")
    monkeypatch.setattr(ps, "_CHUNK_BYTES", 5 * 96 * 72 * 64)  # a few planes per chunk, the last one short
    split = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=MIN_TEXTURE)
    assert torch.equal(one, split)
    monkeypatch.setattr(ps, "_CPU_STRIP", 1)
    single = plane_costs(reference, sources, params, planes, half=HALF, best=2, min_texture=MIN_TEXTURE)
    torch.testing.assert_close(single, one, atol=2e-4, rtol=0)


def test_bad_arguments_are_named(plane):
    cams = plane.cameras
    reference, sources, params, _ = _inputs(cams, plane.images, srcs=(1, 2))
    planes = _fronto(cams[0])
    kw = dict(half=HALF, best=1, min_texture=MIN_TEXTURE)
    with pytest.raises(TypeError, match="reference.gray"):
        plane_costs(reference._replace(gray=reference.gray.double()), sources, params, planes, **kw)
    with pytest.raises(ValueError, match="reference.dirs"):
        plane_costs(reference._replace(dirs=reference.dirs[:, :, :2]), sources, params, planes, **kw)
    with pytest.raises(ValueError, match="sources"):
        plane_costs(reference, sources[:, :10], params, planes, **kw)
    with pytest.raises(ValueError, match="params"):
        plane_costs(reference, sources, params[:1], planes, **kw)
    with pytest.raises(ValueError, match="best"):
        plane_costs(reference, sources, params, planes, half=HALF, best=3, min_texture=MIN_TEXTURE)
    with pytest.raises(ValueError, match="half"):
        plane_costs(reference, sources, params, planes, half=-1, best=1, min_texture=MIN_TEXTURE)
    with pytest.raises(ValueError, match="planes"):
        plane_costs(reference, sources, params, planes[:, None], **kw)
    o, d = cams[0].pixel_rays()
    lv = _level(cams[0], o.float(), d.float())
    with pytest.raises(ValueError, match="planes.lo"):
        plane_costs(reference, sources, params, lv._replace(lo=3.0, hi=1.0), **kw)
