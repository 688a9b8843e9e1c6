# SPDX-License-Identifier: Apache-2.0
"""The fit's trusted rasterize path against the public rasterize_surfels: no validation, near / far defaults
computed on the device, and the deferred pair count with its overflow and capacity growth."""

import numpy as np
import pytest
import torch
from raster_cases import IMAGES, camera, surfels

from wtopo.ops import RasterConfig, rasterize_surfels

# -- the fit's trusted path: no validation, device-side clip defaults, deferred pair count -----------

def _trusted(params, cam, config=None, **kw):
    from wtopo.rasterize import _rasterize_trusted

    bg = torch.tensor([0.1, 0.2, 0.3], dtype=params[0].dtype, device=params[0].device)
    return _rasterize_trusted(*params, cam, sh_degree=None, background=bg, config=config or RasterConfig(), **kw)


def _assert_outputs_equal(a, b, params):
    """Every image, the discrete outputs and the VJP of two renders are bit-identical."""
    for k in (*IMAGES, "visibility", "radii"):
        torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=0, atol=0, msg=k)
    g = torch.Generator().manual_seed(3)
    ups = {k: torch.randn(getattr(a, k).shape, generator=g, dtype=a.rgb.dtype).to(a.rgb.device) for k in IMAGES}
    ga = torch.autograd.grad(sum((getattr(a, k) * u).sum() for k, u in ups.items()), params)
    gb = torch.autograd.grad(sum((getattr(b, k) * u).sum() for k, u in ups.items()), params)
    # CUDA sums the gradients with float atomics whose order varies from run to run (measured on an
    # H100: ~10 % of the entries differ, by up to 1.1e-5 in 1 of 5 runs); CPU sums are ordered
    tol = dict(rtol=1e-3, atol=1e-4) if a.rgb.is_cuda else dict(rtol=0, atol=0)
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, **tol)


@pytest.mark.parametrize("device_clip", [False, True], ids=["host-clip", "device-clip"])
@pytest.mark.parametrize("defer_count", [False, True], ids=["exact-count", "deferred-count"])
def test_trusted_path_equals_public_path(device, device_clip, defer_count):
    """Render bit-identically through the fit's unchecked path, whichever clip and count mode it uses."""
    from wtopo.rasterize import _binning

    _binning._capacities.clear()
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(2):  # the second deferred call uses the capacity the first one measured
        ref = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3))
        out = _trusted(params, cam, device_clip=device_clip, defer_count=defer_count)
        _assert_outputs_equal(out, ref, params)
    assert out.near == ref.near and out.far == ref.far
    if defer_count:
        assert not bool(out.overflow)
    else:
        assert out.overflow is None


@pytest.mark.parametrize("case", ["odd", "even", "none-in-front", "empty"])
def test_device_clip_defaults_equal_host_median(device, case):
    """Compute the default near / far on the device exactly as the host median does."""
    from wtopo.rasterize import _camera as C

    cam = camera()
    n = {"odd": 301, "even": 300, "none-in-front": 50, "empty": 0}[case]
    means = surfels(n, dtype=torch.float32, device=device)[0].detach()
    if case == "none-in-front":
        means = means - torch.tensor([0.0, 0.0, 10.0], device=device)  # every centre behind the camera
    cfg = RasterConfig()
    host = C._default_clip(means, cam, None, None, cfg)
    dev = C._default_clip_device(means, cam, cfg)
    assert dev.dtype == torch.float64
    assert tuple(dev.tolist()) == host


def _settle(cap, device):
    """Let the posted pair counts arrive (CUDA) and observe them; a no-op on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
    cap.poll()


def test_deferred_count_overflow_then_growth(device):
    """Flag a view whose pairs exceed the kept capacity, then grow it: later calls equal fresh ones."""
    from wtopo import _bridge
    from wtopo.rasterize import _binning

    _binning._capacities.clear()
    cam = camera()
    small = surfels(40, dtype=torch.float32, device=device, scale=(0.01, 0.03))
    big = surfels(800, dtype=torch.float32, device=device, seed=1)
    first = _trusted(small, cam, defer_count=True)  # sizes the capacity (one read)
    assert not bool(first.overflow)
    cap = _binning._pair_capacity(_bridge.warp_device(device))
    _settle(cap, device)  # CUDA posts the first count asynchronously: take it in before overriding it
    cap.value = 64  # as if earlier views had been tiny: the big one cannot fit
    over = _trusted(big, cam, defer_count=True)
    assert bool(over.overflow)
    assert torch.isfinite(over.rgb).all()  # incomplete, never out of bounds or NaN
    _settle(cap, device)
    again = _trusted(big, cam, defer_count=True)  # the overflowing count was observed: capacity grown
    assert not bool(again.overflow)
    assert cap.value >= _binning._CAPACITY_MIN
    _assert_outputs_equal(again, rasterize_surfels(*big, cam, background=(0.1, 0.2, 0.3)), big)
    # fewer surfels after more: same results as a fresh call with the larger buffers kept
    _assert_outputs_equal(_trusted(small, cam, defer_count=True),
                          rasterize_surfels(*small, cam, background=(0.1, 0.2, 0.3)), small)


def test_a_smaller_pair_budget_than_the_kept_capacity_is_no_error(device):
    """A deferred call whose ``max_intersections`` is below the capacity an earlier call with a larger budget grew
    renders (its buffers cut to its own budget), equal to the exact count's render."""
    from wtopo import _bridge
    from wtopo.rasterize import _binning

    _binning._capacities.clear()
    cam = camera()
    params = surfels(40, dtype=torch.float32, device=device, scale=(0.01, 0.03))
    cfg = RasterConfig(max_intersections=5000)
    _trusted(params, cam, config=cfg, defer_count=True)  # sizes the capacity
    cap = _binning._pair_capacity(_bridge.warp_device(device))
    _settle(cap, device)
    cap.value = 20_000  # grown by a call with a larger budget
    out = _trusted(params, cam, config=cfg, defer_count=True)
    assert not bool(out.overflow)
    _assert_outputs_equal(out, rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), config=cfg), params)


def _tile_lists(params, cam, monkeypatch, **kw):
    """Each tile's surfel list from the binning of one render (ids as numpy arrays, keyed by tile)."""
    import wtopo.rasterize as R

    got = {}

    def spy(*a, **k):
        got["bins"] = b = real(*a, **k)
        return b

    real = R._bin
    monkeypatch.setattr(R, "_bin", spy)
    _trusted(params, cam, **kw)
    monkeypatch.setattr(R, "_bin", real)
    b = got["bins"]
    start, end = b.tile_start.numpy(), b.tile_end.numpy()
    ids = b.ids.numpy()
    return {t: ids[s:e] for t, (s, e) in enumerate(zip(start, end)) if e > s}


def test_binning_lists_each_tile_front_to_back(device, monkeypatch):
    """Every tile's list holds each surfel once, nearest first, ties in surfel order (the pairs are written in the
    depth order and sorted stably by tile alone); the deferred count's lists, with their padding, are the same."""
    from wtopo.rasterize import _binning

    cam = camera()
    params = [p.detach().clone() for p in surfels(300, dtype=torch.float64, seed=4)]
    params[0][250:] = params[0][200:250]  # exact copies of 50 centres: equal depths
    params = [p.to(device) for p in params]
    _binning._capacities.clear()
    exact = _tile_lists(params, cam, monkeypatch)
    w2c = torch.as_tensor(cam.world_to_camera, dtype=torch.float64)
    depth = (params[0].cpu() @ w2c[:3, :3].T + w2c[:3, 3])[:, 2].numpy()
    assert len(exact) == 20 and sum(len(v) for v in exact.values()) > 1000  # 5 x 4 tiles of 8 px
    ties = 0
    for tile, ids in exact.items():
        assert len(set(ids.tolist())) == len(ids), tile
        d = depth[ids]
        assert (np.diff(d) >= 0).all(), tile
        same = np.diff(d) == 0
        ties += int(same.sum())
        assert (np.diff(ids)[same] > 0).all(), tile
    assert ties > 0  # the copies share tiles
    _binning._capacities.clear()
    _trusted(params, cam, defer_count=True)  # sizes the capacity
    deferred = _tile_lists(params, cam, monkeypatch, defer_count=True)
    assert deferred.keys() == exact.keys()
    for tile, ids in exact.items():
        np.testing.assert_array_equal(deferred[tile], ids)


# -- the op as a function of tensors alone (what the fit's CUDA graph of it captures) ----------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tensor_function_equals_trusted_path(device, dtype):
    """``render_tensors`` (the camera as cached tensors, the sort sized for a given pair capacity, the count
    returned) renders and differentiates as the deferred trusted path with the device clip, bit for bit on the CPU;
    ``shift`` carries the screen-space gradient of ``means2d``; too small a capacity flags an overflow."""
    from wtopo.rasterize import _binning
    from wtopo.rasterize import _graphable as G

    cam = camera()
    cfg = RasterConfig()
    params = surfels(300, dtype=dtype, device=device)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype, device=device)
    ref = _trusted(params, cam, device_clip=True, defer_count=False)
    bins_count = 0
    rays, tables, row4, record = G.view_inputs(cam, torch.device(device), dtype, cfg)
    for pairs in (100_000, 7):
        shift = torch.zeros(300, 2, dtype=dtype, device=device, requires_grad=True)
        outs = G.render_tensors(*params, shift, rays, tables, row4, record, size=G.Size(cam.width, cam.height),
                                sh_degree=2, background=bg, config=cfg, pairs=pairs)
        rgb, alpha, depth, median, normal, dist, vis, radii, m2, clip, overflow, count = outs
        bins_count = int(count)
        assert bool(overflow) == (pairs < bins_count)
        if pairs < bins_count:
            continue
        got = dict(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                   visibility=vis, radii=radii)
        for k, v in got.items():
            torch.testing.assert_close(v, getattr(ref, k), rtol=0, atol=0, msg=k)
        torch.testing.assert_close(m2, ref.means2d.detach(), rtol=0, atol=0)
        torch.testing.assert_close(clip, ref.clip, rtol=0, atol=0)
        g = torch.Generator().manual_seed(3)
        ups = {k: torch.randn(getattr(ref, k).shape, generator=g, dtype=dtype).to(device) for k in IMAGES}
        ga = torch.autograd.grad(sum((got[k] * u).sum() for k, u in ups.items()), [*params, shift])
        gb = torch.autograd.grad(sum((getattr(ref, k) * u).sum() for k, u in ups.items()), [*params, ref.means2d])
        tol = dict(rtol=1e-3, atol=1e-4) if rgb.is_cuda else dict(rtol=0, atol=0)
        for x, y in zip(ga, gb):
            assert float(y.abs().max()) > 0
            torch.testing.assert_close(x, y, **tol)
    _binning._capacities.clear()
    assert bins_count > 7


# -- a render nothing differentiates: no tape, the records prepared and packed in one kernel ---------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sh", [16, 0], ids=["sh3", "rgb"])
def test_a_render_without_gradients_equals_a_differentiable_one(device, dtype, sh, monkeypatch):
    """Under no_grad (no tape: the fused preparation, no gradient arrays) every output equals the differentiable
    render's, bit for bit, surfels behind the camera and edge-on ones included; on CUDA the warp-cooperative
    kernels too. The two-kernel preparation gives the same without gradients."""
    from wtopo.rasterize import _run

    params = surfels(400, dtype=dtype, device=device, sh=sh)
    with torch.no_grad():
        params[0][:5] = torch.tensor([0.3, -0.2, -3.4], dtype=dtype, device=device)  # behind the camera
        params[1][5:10] = torch.tensor([0.7071, 0.7071, 0.0, 0.0], dtype=dtype, device=device)  # edge-on to the view
    cam = camera(45, 33, distortion=(0.05, -0.01, 0.001, 0.0, 0.0))
    cfg = RasterConfig(replay=False)
    want = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), config=cfg)
    for fused in (True, False):
        monkeypatch.setattr(_run, "FUSED_FORWARD", fused)
        with torch.no_grad():
            got = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), config=cfg)
        for k in (*IMAGES, "visibility", "radii", "means2d"):
            torch.testing.assert_close(getattr(got, k), getattr(want, k).detach(), rtol=0, atol=0, msg=(fused, k))
        assert not got.rgb.requires_grad
