# SPDX-License-Identifier: Apache-2.0
"""The fit's replayed renders (``wtopo.fitting.raster_graph``): with the capture emulated (the function itself
stands in for its graphs) on every device, and captured on CUDA, a render equals the fit's eager deferred render,
gradients and the screen-space statistic included; one capture serves every view of a size; a new surfel count
captures again; a capture that fails or disagrees turns the graphs off with a warning."""

from __future__ import annotations

import pytest
import torch
from graph_standins import static_buffers
from raster_cases import IMAGES, camera

import wtopo
from wtopo.fitting import raster_graph as RG
from wtopo.fitting.stages import Renderer
from wtopo.fitting.surfels import Surfels
from wtopo.rasterize import RasterConfig, _binning, _rasterize_trusted


def _emulate(fn, samples, num_warmup_iters=0):  # torch.cuda.make_graphed_callables' signature, no capture
    return fn


def _altered_replay(change):
    """A ``make`` whose replays return the function's outputs with output 0 (the image) passed through ``change``."""
    def make(fn, samples, num_warmup_iters=0):
        def replay(*args):
            out = list(fn(*args))
            out[0] = change(out[0])
            return tuple(out)
        return replay
    return make


def _surfels(n, device, seed=0, sh_rest=3):
    g = torch.Generator().manual_seed(seed)
    return Surfels(means=(torch.rand(n, 3, generator=g) - 0.5).to(device),
                   quats=torch.randn(n, 4, generator=g).to(device),
                   log_scales=(torch.rand(n, 2, generator=g) * 2 - 4.5).to(device),
                   opacity_logits=torch.randn(n, generator=g).to(device),
                   sh_dc=(torch.rand(n, 1, 3, generator=g) - 0.5).to(device),
                   sh_rest=(torch.randn(n, sh_rest, 3, generator=g) * 0.1).to(device))


def _cameras():
    other = wtopo.Camera.look_at([0.9, 0.4, -2.7], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=37, height=29)
    return [camera(), other]


def _eager(s, cam, bg, cfg):
    return _rasterize_trusted(s.means, s.quats, s.scales, s.opacities, s.sh, cam, sh_degree=s.sh_degree,
                              background=bg, config=cfg, defer_count=True, device_clip=True)


def _measured(device, n=200):
    """Surfels whose pair count the capacity has seen (an eager deferred render, settled), as a fit's first render
    leaves it."""
    _binning._capacities.clear()
    s = _surfels(n, device)
    _eager(s, camera(), torch.zeros(3, device=device), RasterConfig())
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    return s


def _compare(got, want, s, tol):
    for k in (*IMAGES, "visibility", "radii", "clip"):
        torch.testing.assert_close(getattr(got, k), getattr(want, k), **tol, msg=k)
    assert not bool(got.overflow)
    g = torch.Generator().manual_seed(4)
    ups = {k: torch.randn(getattr(want, k).shape, generator=g).to(want.rgb.device) for k in IMAGES}
    leaves = list(s.params.values())
    ga = torch.autograd.grad(sum((getattr(got, k) * u).sum() for k, u in ups.items()), [*leaves, got.means2d],
                             allow_unused=True)
    gb = torch.autograd.grad(sum((getattr(want, k) * u).sum() for k, u in ups.items()), [*leaves, want.means2d],
                             allow_unused=True)
    for a, b in zip(ga, gb):
        assert a is not None and b is not None
        torch.testing.assert_close(a, b, **tol)
    assert float(gb[0].abs().max()) > 0 and float(gb[-1].abs().max()) > 0


def _modes(device):
    modes = [("emulated", _emulate), ("static buffers", static_buffers)]
    if str(device).startswith("cuda"):
        modes.append(("captured", None))
    return modes


def test_replayed_renders_equal_the_eager_render(device):
    """Over two views, two surfel counts and a second render of each, a replay renders and differentiates as the
    eager deferred render (bit for bit on the CPU; CUDA's gradients are sums of float atomics); one capture per
    surfel count."""
    cfg = RasterConfig()
    bg = torch.tensor([0.1, 0.2, 0.3], device=device)
    tol = dict(rtol=1e-4, atol=1e-5) if str(device).startswith("cuda") else dict(rtol=0, atol=0)
    for label, make in _modes(device):
        _binning._capacities.clear()
        graphs = RG.RasterGraphs(bg, cfg, make=make)
        for n in (200, 260):
            s = _surfels(n, device, seed=n)
            for rep in range(2):
                before = graphs.captures
                for cam in _cameras():
                    want = _eager(s, cam, bg, cfg)  # also measures the pair capacity (the first one on CUDA reads it)
                    if str(device).startswith("cuda"):
                        torch.cuda.synchronize()
                    got = graphs(s, cam)
                    assert got is not None, (label, graphs.failure)
                    _compare(got, want, s, tol)
                if rep == 1:  # the capacity has seen both views: one capture serves them
                    assert graphs.captures == before, label
        assert graphs.failure is None and graphs.captures >= 2, label
    _binning._capacities.clear()


def test_a_render_that_disagrees_turns_the_graphs_off(device, monkeypatch):
    """A capture whose replay differs from the eager render (here a stand-in that brightens the image) is not used:
    the call returns None (the caller renders eagerly), warns, and the graphs stay off."""
    cfg = RasterConfig()
    bg = torch.zeros(3, device=device)

    s = _measured(device)
    graphs = RG.RasterGraphs(bg, cfg, make=_altered_replay(lambda rgb: rgb + 0.01))
    with pytest.warns(RuntimeWarning, match="output 0 of a replay differs"):
        assert graphs(s, camera()) is None
    assert "differs" in graphs.failure
    assert graphs(s, camera()) is None  # off for good, no second warning
    _binning._capacities.clear()


def test_no_graph_without_gradients_surfels_or_a_capacity(device):
    cfg = RasterConfig()
    bg = torch.zeros(3, device=device)
    _binning._capacities.clear()
    graphs = RG.RasterGraphs(bg, cfg, make=_emulate)
    s = _surfels(50, device)
    assert graphs(s, camera()) is None  # no pair count measured yet
    _eager(s, camera(), bg, cfg)
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
    with torch.no_grad():
        assert graphs(s, camera()) is None
    assert graphs(_surfels(0, device), camera()) is None
    assert graphs(s, camera()) is not None
    _binning._capacities.clear()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the fit's renderer replays graphs on CUDA only")
def test_the_fit_renderer_replays_deferred_renders():
    from conftest import CUDA_DEVICE

    _binning._capacities.clear()
    bg = torch.zeros(3, device=CUDA_DEVICE)
    r = Renderer(bg, RasterConfig(), graphs=True)
    s = _surfels(300, CUDA_DEVICE)
    r(s, camera(), defer_count=True)  # measures the capacity
    torch.cuda.synchronize()
    out = r(s, camera(), defer_count=True)
    assert r.graphs.failure is None and r.graphs.captures == 1
    assert out.means2d.requires_grad and float(out.means2d.abs().max()) == 0.0  # the gradient carrier
    _binning._capacities.clear()


def test_a_replay_with_wrong_gradients_turns_the_graphs_off(device):
    """The first replay's gradients are checked too: a stand-in with the right images and doubled image gradients is
    not used."""
    cfg = RasterConfig()
    bg = torch.zeros(3, device=device)

    s = _measured(device)
    twice = _altered_replay(lambda rgb: rgb.detach() + (rgb - rgb.detach()) * 2.0)  # same values, twice the gradient
    graphs = RG.RasterGraphs(bg, cfg, make=twice)
    with pytest.warns(RuntimeWarning, match="gradient of input 0 of a replay differs"):
        assert graphs(s, camera()) is None
    _binning._capacities.clear()


def test_captures_on_most_renders_turn_the_graphs_off(device, monkeypatch):
    """Renders that need a new capture nearly every time (here a surfel count that changes at every call) turn the
    graphs off once the captures outnumber one in twenty renders."""
    monkeypatch.setattr(RG, "_CHURN_CALLS", 5)
    cfg = RasterConfig()
    bg = torch.zeros(3, device=device)
    _binning._capacities.clear()
    graphs = RG.RasterGraphs(bg, cfg, make=_emulate)
    with pytest.warns(RuntimeWarning, match="captures in"):
        for k in range(8):
            s = _surfels(100 + k, device, seed=k)
            _eager(s, camera(), bg, cfg)
            if str(device).startswith("cuda"):
                torch.cuda.synchronize()
            out = graphs(s, camera())
            if graphs.failure is not None:
                break
    assert out is None and "captures in" in graphs.failure and k == 5
    _binning._capacities.clear()


def test_the_sorted_capacity_rounds_up_by_steps_of_sqrt2():
    budget = RG.pair_budget
    assert budget(1000, 10**9) == 1024 and budget(1024, 10**9) == 1024 and budget(1025, 10**9) == 1449
    assert budget(5000, 4096) == 4096 and budget(1, 10) == 1
