# SPDX-License-Identifier: Apache-2.0
"""Repeated public calls replayed as CUDA graphs (``wtopo.rasterize._replay``): on the CPU with a stand-in for the
capture that keeps a graph's buffer semantics (outputs and gradients in fixed buffers the next call overwrites),
on CUDA captured. A replayed call equals the eager one (images, per-surfel outputs, clip planes, the projected
centres and every gradient, ``means2d``'s included); what a caller holds survives the next call; a second render
before the first one's backward, a view with more pairs than the graph sorts for, a failed capture, explicit clip
planes and a profiled section all render eagerly."""

from __future__ import annotations

import contextlib
import dataclasses

import pytest
import torch
from graph_standins import fixed_outputs, latest_state, static_buffers
from raster_cases import IMAGES, camera, surfels

import wtopo
from wtopo._profile import section
from wtopo.ops import RasterConfig, rasterize_surfels
from wtopo.rasterize import _replay


@pytest.fixture(autouse=True)
def _fresh(device, monkeypatch):
    """Replays on, no shape known; on the CPU the capture is the buffer-keeping stand-in."""
    _replay.reset()
    cuda = str(device).startswith("cuda")
    monkeypatch.setattr(_replay, "_MAKE", None if cuda else static_buffers)
    monkeypatch.setattr(_replay, "_CAPTURE", None if cuda else fixed_outputs)
    yield
    _replay.reset()


BG = (0.1, 0.2, 0.3)


def _eager(params, cam, background=BG, config=None):
    config = dataclasses.replace(config or RasterConfig(), replay=False)
    return rasterize_surfels(*params, cam, background=background, config=config)


def _close_grads(a, b, cuda):
    """Equal on the CPU (ordered sums); on CUDA, whose float atomics sum in a varying order, within 1e-3 of the
    largest entry (an entry that nearly cancels moves by a fraction of the largest one)."""
    if not cuda:
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        return
    assert float((a - b).abs().max()) <= 1e-3 * float(b.abs().max()) + 1e-9


def _snapshot(out, params, seed=3):
    """The outputs and the gradients of a fixed weighting of the images (``means2d``'s included) of ``out``,
    as copies; the gradients are left in the leaves' ``.grad``."""
    for p in params:
        p.grad = None
    g = torch.Generator().manual_seed(seed)
    ups = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=out.rgb.dtype).to(out.rgb.device)
           for k in IMAGES}
    sum((getattr(out, k) * u).sum() for k, u in ups.items()).backward()
    snap = {k: getattr(out, k).detach().clone() for k in (*IMAGES, "visibility", "radii", "clip")}
    snap["means2d"] = out.means2d.detach().clone()
    snap["near_far"] = (out.near, out.far)
    snap["grads"] = [p.grad.clone() for p in (*params, out.means2d)]
    return snap


def _assert_same(a, b, cuda):
    for k in (*IMAGES, "visibility", "radii", "clip", "means2d"):
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert a["near_far"] == b["near_far"]
    for x, y in zip(a["grads"], b["grads"]):
        _close_grads(x, y, cuda)


def _first_calls(params, cam, make, monkeypatch):
    """The exact calls before a capture, with ``make`` standing in for the capture (``None``: CUDA's own)."""
    monkeypatch.setattr(_replay, "_MAKE", make)
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)


def _shape():
    (shape,) = _replay._shapes.values()
    return shape


@pytest.mark.parametrize("sh", [9, 0], ids=["sh", "rgb"])
def test_replayed_calls_equal_eager_calls(device, sh):
    """The first EAGER_CALLS calls render eagerly, then a capture; every later call replays and equals the eager
    render of its own values, gradients and the screen-space gradient included."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device, sh=sh)
    for k in range(_replay.EAGER_CALLS + 3):
        with torch.no_grad():
            params[0].add_(0.002)  # each call its own values, as a training loop's steps
        out = rasterize_surfels(*params, cam, background=BG)
        got = _snapshot(out, params)
        want = _snapshot(_eager(params, cam), params)
        _assert_same(got, want, out.rgb.is_cuda)
        assert _shape().replays == max(0, k + 1 - _replay.EAGER_CALLS)
    assert _replay.failure is None


def _same_forward(out, want):
    for k in (*IMAGES, "visibility", "radii", "means2d", "clip"):
        torch.testing.assert_close(getattr(out, k), getattr(want, k), rtol=0, atol=0, msg=k)
    assert (out.near, out.far) == (want.near, want.far)
    assert not out.rgb.requires_grad and not out.means2d.requires_grad


def _turned(cam, angle):
    """``cam`` turned by ``angle`` about the vertical axis through the origin (the same size: the same shape)."""
    c, s = torch.cos(torch.tensor(angle)).item(), torch.sin(torch.tensor(angle)).item()
    eye = [0.3 * c - 3.0 * s, -0.2, 0.3 * s - 3.0 * c]
    return wtopo.Camera.look_at(eye, [0, 0, 0], [0, -1, 0], fov_x=0.9, width=cam.width, height=cam.height)


@pytest.mark.parametrize("mode", ["no_grad", "no input requiring grad"])
def test_a_forward_replay_reads_the_callers_tensors_where_they_lie(device, mode):
    """Calls no gradient can reach, their tensors updated in place (a loop's parameters): the capture after
    EAGER_CALLS reads them where they lie, with no copies, and every replay equals the eager render of what they
    hold at that call, in each of two views of one size taken in turn."""
    cams = [camera(), _turned(camera(), 0.4)]
    params = surfels(300, dtype=torch.float32, device=device)
    if mode != "no_grad":
        params = [p.detach() for p in params]
    for k in range(_replay.EAGER_CALLS + 4):
        with torch.no_grad():
            params[0].add_(0.002)
            params[4].mul_(0.99)
        with torch.no_grad() if mode == "no_grad" else contextlib.nullcontext():
            assert torch.is_grad_enabled() == (mode != "no_grad")
            out = rasterize_surfels(*params, cams[k % 2], background=BG)
            _same_forward(out, _eager(params, cams[k % 2]))
    shape = _shape()
    assert shape.replays == 4 and shape.graphed.reads is not None and shape.graphed.inputs is None


def test_a_forward_replay_of_moved_tensors_renders_them_and_then_copies(device):
    """A call whose tensors lie elsewhere than the in-place capture reads renders eagerly (exact), and the shape
    is captured again copying its inputs, so tensors made afresh at every call replay too."""
    cam = camera()
    params = [p.detach() for p in surfels(300, dtype=torch.float32, device=device)]
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    assert _shape().graphed.reads is not None
    kept = []
    for k in range(_replay.EAGER_CALLS + 3):
        fresh = [p + 0.001 * (k + 1) * (j == 0) for j, p in enumerate(params)]  # new tensors, new addresses
        kept.append(fresh)  # held: no address is handed back to a later call
        out = rasterize_surfels(*fresh, cam, background=BG)
        _same_forward(out, _eager(fresh, cam))
    shape = _shape()
    assert shape.replays == 3 and shape.graphed.reads is None and shape.graphed.inputs is not None
    assert not shape.steady


def test_a_forward_replays_outputs_are_the_callers(device):
    """What a forward replay returned survives the next replay of other values."""
    cam = camera()
    params = [p.detach() for p in surfels(300, dtype=torch.float32, device=device)]
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    out = rasterize_surfels(*params, cam, background=BG)
    held = {k: getattr(out, k) for k in (*IMAGES, "visibility", "radii", "means2d")}
    copies = {k: v.clone() for k, v in held.items()}
    params[0].add_(0.05)
    nxt = rasterize_surfels(*params, cam, background=(0.9, 0.1, 0.1))
    assert _shape().replays == 2 and not torch.equal(nxt.rgb, out.rgb)
    _same_forward(nxt, _eager(params, cam, background=(0.9, 0.1, 0.1)))  # this call's background, not the last
    for k, v in held.items():
        torch.testing.assert_close(v, copies[k], rtol=0, atol=0, msg=k)


def test_a_forward_replay_with_more_pairs_than_it_sorts_for_renders_exactly(device):
    """A forward replay whose view outgrew the capture renders eagerly (exact); the shape is captured again for the
    larger count, in place, and replays."""
    cam = camera()
    params = [p.detach() for p in surfels(300, dtype=torch.float32, device=device, scale=(0.01, 0.03))]
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    small = _shape().most_pairs
    params[2].mul_(8.0)
    out = rasterize_surfels(*params, cam, background=BG)
    assert _shape().replays == 0 and _shape().most_pairs > small
    _same_forward(out, _eager(params, cam))
    out = rasterize_surfels(*params, cam, background=BG)
    assert _shape().replays == 1 and _shape().graphed.reads is not None
    _same_forward(out, _eager(params, cam))


@pytest.mark.parametrize("case", ["raises", "disagrees"])
def test_a_forward_capture_that_fails_or_disagrees(device, case, monkeypatch):
    """A forward capture that raises leaves its shape eager with a warning; one whose first replay differs from
    the eager render of that call turns replays off for the process."""
    def broken(fn, args, warmup):
        if case == "raises":
            raise RuntimeError("no capture here")
        replay, outs = fixed_outputs(fn, args, warmup)
        return (lambda: (replay(), outs[0].add_(1e-3))), outs

    monkeypatch.setattr(_replay, "_CAPTURE", broken)
    cam = camera()
    params = [p.detach() for p in surfels(300, dtype=torch.float32, device=device)]
    with pytest.warns(RuntimeWarning, match="no capture here" if case == "raises" else "output 0 of a replay differs"):
        for _ in range(_replay.EAGER_CALLS):
            rasterize_surfels(*params, cam, background=BG)
    if case == "raises":
        assert _shape().failed and _replay.failure is None
    else:
        assert _replay.failure is not None
    _same_forward(rasterize_surfels(*params, cam, background=BG), _eager(params, cam))


def test_forward_and_differentiable_calls_are_shapes_apart(device):
    """The same surfels rendered with and without gradients: two shapes, each captured in its own way."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(_replay.EAGER_CALLS + 1):
        rasterize_surfels(*params, cam, background=BG)
        with torch.no_grad():
            rasterize_surfels(*params, cam, background=BG)
    grad_shape, fwd_shape = _replay._shapes.values()
    assert grad_shape.replays == 1 and fwd_shape.replays == 1
    assert isinstance(fwd_shape.graphed, _replay._Forward) and not isinstance(grad_shape.graphed, _replay._Forward)


def test_what_a_caller_holds_survives_the_next_call(device):
    """A replay's images and the gradients it left in ``.grad`` are the caller's, not the graph's buffers."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    out = rasterize_surfels(*params, cam, background=BG)
    held = {k: getattr(out, k) for k in (*IMAGES, "visibility", "radii", "means2d")}
    copies = {k: v.detach().clone() for k, v in held.items()}
    out.rgb.sum().backward()
    grads = [p.grad for p in params] + [out.means2d.grad]
    grad_copies = [g.clone() for g in grads]
    with torch.no_grad():
        moved = [p + 0.002 * torch.rand_like(p) for p in params]  # scales stay > 0, opacities < 1
    moved = [m.requires_grad_(True) for m in moved]
    nxt = rasterize_surfels(*moved, cam, background=BG)
    (nxt.alpha * 3.0).sum().backward()
    assert _shape().replays == 2
    for k, v in held.items():
        torch.testing.assert_close(v.detach(), copies[k], rtol=0, atol=0, msg=k)
    for g, c in zip(grads, grad_copies):
        torch.testing.assert_close(g, c, rtol=0, atol=0)


def test_a_render_before_the_last_ones_backward_is_eager(device):
    """Two renders of one shape, one loss: the second renders eagerly (a replay would overwrite what the first
    one's backward reads), and the gradients are those of two eager renders."""
    cam = camera()
    other = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    a = rasterize_surfels(*params, cam, background=BG)
    b = rasterize_surfels(*params, other, background=(0.5, 0.5, 0.5))
    assert _shape().replays == 1
    (a.rgb.sum() + 2.0 * b.depth.sum()).backward()
    got = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    ea, eb = _eager(params, cam), _eager(params, other, background=(0.5, 0.5, 0.5))
    (ea.rgb.sum() + 2.0 * eb.depth.sum()).backward()
    for x, p in zip(got, params):
        _close_grads(x, p.grad, a.rgb.is_cuda)
    # once the backward has run, the shape replays again
    rasterize_surfels(*params, cam, background=BG)
    assert _shape().replays == 2


def test_a_dropped_render_frees_the_shape(device):
    """Outputs dropped without a backward do not hold the shape eager."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(_replay.EAGER_CALLS + 1):
        out = rasterize_surfels(*params, cam, background=BG)
    del out
    rasterize_surfels(*params, cam, background=BG)
    assert _shape().replays == 2


def test_more_pairs_than_the_graph_sorts_for_render_exactly(device):
    """A view whose pair count outgrows the capture renders again eagerly (exact), and the shape is captured again
    for the larger count."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device, scale=(0.01, 0.03))
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    small = _shape().most_pairs
    with torch.no_grad():
        params[2].mul_(8.0)  # larger disks: more tiles each
    out = rasterize_surfels(*params, cam, background=BG)
    assert _shape().replays == 0 and _shape().most_pairs > small
    _assert_same(_snapshot(out, params), _snapshot(_eager(params, cam), params), out.rgb.is_cuda)
    out = rasterize_surfels(*params, cam, background=BG)  # the new capture's first replay
    assert _shape().replays == 1
    _assert_same(_snapshot(out, params), _snapshot(_eager(params, cam), params), out.rgb.is_cuda)


def test_a_capture_that_raises_leaves_its_shape_eager_with_a_warning(device, monkeypatch):
    def broken(fn, samples, num_warmup_iters=0):
        raise RuntimeError("no capture here")

    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    with pytest.warns(RuntimeWarning, match="no capture here"):
        _first_calls(params, cam, broken, monkeypatch)
    assert _shape().failed and _replay.failure is None
    out = rasterize_surfels(*params, cam, background=BG)
    _assert_same(_snapshot(out, params), _snapshot(_eager(params, cam), params), out.rgb.is_cuda)
    assert _shape().replays == 0


def test_a_replay_that_disagrees_turns_replays_off(device, monkeypatch):
    def altered(fn, samples, num_warmup_iters=0):
        replay = static_buffers(fn, samples)
        return lambda *a: (replay(*a)[0] + 1e-3, *replay(*a)[1:])

    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    with pytest.warns(RuntimeWarning, match="output 0 of a replay differs"):
        _first_calls(params, cam, altered, monkeypatch)
    assert _replay.failure is not None


@pytest.mark.parametrize("case", ["explicit-clip", "profiled", "inference-mode", "autocast", "replay-off"])
def test_calls_that_never_replay(device, case, monkeypatch):
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    kw = {"near": 0.5, "far": 10.0} if case == "explicit-clip" else {}
    if case == "replay-off":
        kw = {"config": RasterConfig(replay=False)}
    for _ in range(_replay.EAGER_CALLS + 2):
        if case == "profiled":
            with section("outer", add=lambda name, dt: None):
                rasterize_surfels(*params, cam, background=BG, **kw)
        elif case == "inference-mode":
            with torch.inference_mode():
                rasterize_surfels(*params, cam, background=BG, **kw)
        elif case == "autocast":
            with torch.autocast(torch.device(device).type, dtype=torch.bfloat16):
                rasterize_surfels(*params, cam, background=BG, **kw)
        else:
            rasterize_surfels(*params, cam, background=BG, **kw)
    assert all(s.graphed is None and s.replays == 0 for s in _replay._shapes.values())


def test_only_the_newest_shapes_keep_their_captures(device):
    cam = camera()
    sizes = (100, 120, 140, 160)
    for n in sizes:
        params = surfels(n, dtype=torch.float32, device=device)
        for _ in range(_replay.EAGER_CALLS):
            rasterize_surfels(*params, cam, background=BG)
    captured = [key[2] for key, s in _replay._shapes.items() if s.graphed is not None]
    assert captured == list(sizes[-_replay.KEPT:])
    first = next(iter(_replay._shapes.values()))
    assert first.graphed is None and first.needed == 2 * _replay.EAGER_CALLS


def test_shapes_in_turn_do_not_capture_at_every_call(device, monkeypatch):
    """More shapes in turn than KEPT: a dropped shape waits twice as long before its next capture."""
    made = []

    def counting(fn, samples, num_warmup_iters=0):
        made.append(1)
        return static_buffers(fn, samples)

    monkeypatch.setattr(_replay, "_MAKE", counting)
    params = surfels(200, dtype=torch.float32, device=device)
    cams = [camera(20 + 3 * k, 17) for k in range(_replay.KEPT + 1)]
    calls = 48
    for k in range(calls):
        rasterize_surfels(*params, cams[k % len(cams)], background=BG)
    replays = sum(s.replays for s in _replay._shapes.values())
    assert len(made) <= 10 and replays >= calls // 2, (len(made), replays)


def test_bad_input_still_raises_before_a_replay(device):
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    for _ in range(_replay.EAGER_CALLS):
        rasterize_surfels(*params, cam, background=BG)
    with torch.no_grad():
        params[3][7] = 1.5
    with pytest.raises(ValueError, match="opacities"):
        rasterize_surfels(*params, cam, background=BG)


def test_replays_keep_the_settings_apart(device):
    """Another configuration or image size is another shape, captured and replayed on its own."""
    params = surfels(300, dtype=torch.float32, device=device)
    for cfg in (RasterConfig(), RasterConfig(tile_size=16)):
        for cam in (camera(), camera(41, 23)):
            for _ in range(_replay.EAGER_CALLS + 1):
                out = rasterize_surfels(*params, cam, background=BG, config=cfg)
            assert next(reversed(_replay._shapes.values())).replays == 1
            want = _eager(params, cam, config=cfg)
            torch.testing.assert_close(out.rgb, want.rgb, rtol=0, atol=0)


def _captured(params, cam, make, monkeypatch):
    _first_calls(params, cam, make, monkeypatch)
    assert _shape().graphed is not None


@pytest.mark.parametrize("retain", [True, False], ids=["retain-graph", "plain"])
def test_a_replay_is_differentiated_once(device, retain, monkeypatch):
    """The first backward gives the eager render's gradients and frees the shape for the next replay; a second
    backward through the same replay raises (its graph would add into the gradient buffers again), with or without
    retain_graph, and RasterConfig(replay=False) renders what can be differentiated twice."""
    cam = camera()
    params = surfels(300, dtype=torch.float32, device=device)
    _captured(params, cam, None if str(device).startswith("cuda") else latest_state, monkeypatch)
    a = rasterize_surfels(*params, cam, background=BG)
    la = (a.rgb * 2.0).sum() + a.depth.sum()
    first = torch.autograd.grad(la, params, retain_graph=retain)
    want = _eager(params, cam)
    for x, y in zip(first, torch.autograd.grad((want.rgb * 2.0).sum() + want.depth.sum(), params)):
        _close_grads(x, y, a.rgb.is_cuda)
    rasterize_surfels(*params, cam, background=BG)  # the backward ran: the shape replays again
    assert _shape().replays == 2
    with pytest.raises(RuntimeError, match="differentiated once" if retain else "second time|freed|once"):
        torch.autograd.grad(la, params)
    e = _eager(params, cam)
    le = (e.rgb * 2.0).sum() + e.depth.sum()
    g1, g2 = torch.autograd.grad(le, params, retain_graph=True), torch.autograd.grad(le, params)
    for x, y in zip(g1, g2):
        _close_grads(x, y, e.rgb.is_cuda)


@pytest.mark.parametrize("dtype", [torch.float64])
@pytest.mark.parametrize("which", [(0,), (2, 4)], ids=["means-only", "scales-and-colours"])
def test_some_inputs_requiring_grad(device, dtype, which, monkeypatch):
    """Only some inputs require grad, float64: the replay's gradients are the eager render's, the others None."""
    cam = camera()
    params = [p.detach().requires_grad_(k in which) for k, p in enumerate(surfels(300, dtype=dtype, device=device))]
    _captured(params, cam, None if str(device).startswith("cuda") else latest_state, monkeypatch)
    out = rasterize_surfels(*params, cam, background=BG)
    want = _eager(params, cam)
    assert _shape().replays == 1 and not out.clip.requires_grad
    diff = [params[k] for k in which]
    ga = torch.autograd.grad((out.rgb * 1.5).sum() + out.normal.sum(), diff)
    gb = torch.autograd.grad((want.rgb * 1.5).sum() + want.normal.sum(), diff)
    for x, y in zip(ga, gb):
        _close_grads(x, y, out.rgb.is_cuda)
    assert all(params[k].grad is None for k in range(5))


def test_the_replay_setting_is_checked(device):
    params = surfels(30, dtype=torch.float32, device=device)
    with pytest.raises(TypeError, match="config.replay must be a bool"):
        rasterize_surfels(*params, camera(), config=RasterConfig(replay=1))
