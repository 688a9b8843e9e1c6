# SPDX-License-Identifier: Apache-2.0
"""The torch <-> Warp bridge: gradients, reentrancy, non-differentiable outputs, split launches."""

from typing import Any

import numpy as np
import pytest
import torch
import warp as wp

import wtopo  # noqa: F401  (mounts wtopo.kernels in a source tree)
from wtopo import _bridge


@wp.kernel
def _square_sum_kernel(x: wp.array[Any], y: wp.array[Any], out: wp.array[Any], flag: wp.array[wp.int32]):
    i = wp.tid()
    out[i] = x[i] * x[i] + y[i] * type(x[i])(3.0)
    flag[i] = wp.int32(1)


@wp.kernel
def _double_vec4_kernel(x: wp.array[wp.vec4d], out: wp.array[wp.vec4d]):
    i = wp.tid()
    out[i] = wp.float64(2.0) * x[i]


def _run_double_vec4(x):
    out = wp.zeros(x.shape, dtype=x.dtype, device=x.device, requires_grad=True)
    wp.launch(_double_vec4_kernel, dim=x.shape[0], inputs=[x], outputs=[out], device=x.device)
    return (out,)


@wp.kernel
def _offset_kernel(offset: int, x: wp.array[float], out: wp.array[float]):
    i = wp.tid() + offset
    out[i] = x[i] + float(i)


def _run(x, y):
    out = wp.zeros(x.shape, dtype=x.dtype, device=x.device, requires_grad=True)
    flag = wp.zeros(x.shape, dtype=wp.int32, device=x.device)
    wp.launch(_square_sum_kernel, dim=x.shape[0], inputs=[x, y], outputs=[out, flag], device=x.device)
    return out, flag


def _op(dtype):
    wdt = wp.float64 if dtype == torch.float64 else wp.float32
    return _bridge.WarpOp("square_sum", _run, (wdt, wdt), (True, True), (True, False))


def test_bridge_gradcheck_float64(device):
    """Match torch's finite differences through the bridge, including repeated backward calls."""
    x = torch.randn(7, dtype=torch.float64, device=device, requires_grad=True)
    y = torch.randn(7, dtype=torch.float64, device=device, requires_grad=True)
    op = _op(torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: _bridge.apply(op, a, b)[0], (x, y))


def test_bridge_no_double_gradients(device):
    """Return the same gradient when the graph is differentiated twice (tape.zero between)."""
    x = torch.randn(5, device=device, requires_grad=True)
    y = torch.randn(5, device=device, requires_grad=True)
    out, flag = _bridge.apply(_op(torch.float32), x, y)
    assert not flag.requires_grad
    g1 = torch.autograd.grad(out.sum(), (x, y), retain_graph=True)
    g2 = torch.autograd.grad(out.sum(), (x, y))
    torch.testing.assert_close(g1[0], 2 * x.detach())
    torch.testing.assert_close(g1[1], torch.full_like(y, 3.0))
    torch.testing.assert_close(g1[0], g2[0])
    torch.testing.assert_close(g1[1], g2[1])


def _run_chain(x, y):
    # an intermediate array between two recorded launches: its gradient buffer is the bridge's to clear
    mid, flag = _run(x, y)
    return _run(mid, y)


def test_bridge_accumulates_repeated_backward_into_grad_without_touching_the_first(device):
    """Backward twice through an op with an intermediate array (retain_graph), into .grad and into a kept
    gradient: the second adds the same amount and leaves what the first handed to torch as it was; an input
    sliced with an odd stride on a size-1 dimension gets its gradient too."""
    wdt = wp.float64
    op = _bridge.WarpOp("chain", _run_chain, (wdt, wdt), (True, True), (True, False))
    x = torch.randn(6, dtype=torch.float64, device=device, requires_grad=True)
    y = torch.randn(6, dtype=torch.float64, device=device, requires_grad=True)
    out, _ = _bridge.apply(op, x, y)
    mid = x.detach() ** 2 + 3 * y.detach()
    want_x, want_y = 4 * mid * x.detach(), 2 * mid * 3 + 3  # d/dx, d/dy of sum((x^2 + 3y)^2 + 3y)
    first = torch.autograd.grad(out.sum(), (x, y), retain_graph=True)
    kept = [g.clone() for g in first]
    out.sum().backward(retain_graph=True)
    out.sum().backward()
    torch.testing.assert_close(x.grad, 2 * want_x)
    torch.testing.assert_close(y.grad, 2 * want_y)
    for g, k, w in zip(first, kept, (want_x, want_y)):
        torch.testing.assert_close(g, k)
        torch.testing.assert_close(g, w)
    wide = torch.randn(1, 6, dtype=torch.float64, device=device, requires_grad=True)
    sliced = wide[:, :4]  # contiguous for torch, stride 6 on its size-1 dimension
    vec_op = _bridge.WarpOp("double_vec4", _run_double_vec4, (wp.vec4d,), (True,), (True,))
    (out,) = _bridge.apply(vec_op, sliced)
    out.sum().backward()
    torch.testing.assert_close(wide.grad, torch.tensor([[2.0, 2, 2, 2, 0, 0]], dtype=torch.float64, device=device))


def test_bridge_partial_requires_grad(device):
    """Give None for inputs that do not require grad."""
    x = torch.randn(5, device=device, requires_grad=True)
    y = torch.randn(5, device=device)
    out, _ = _bridge.apply(_op(torch.float32), x, y)
    out.sum().backward()
    torch.testing.assert_close(x.grad, 2 * x.detach())
    assert y.grad is None


@pytest.mark.parametrize("mode", ["no_grad", "no input requiring grad", "a non-differentiable input"])
def test_an_op_no_gradient_can_reach_runs_without_a_tape(device, mode):
    """Where no gradient can flow, the op runs with no tape active (``active_tape()`` is None inside ``run``) and
    gives the values of a taped run, as plain tensors."""
    seen = []

    def run(x, y):
        seen.append(_bridge.active_tape())
        return _run(x, y)

    diff = (True, mode != "a non-differentiable input")
    op = _bridge.WarpOp("square_sum", run, (wp.float32, wp.float32), (diff[0] and diff[1], True), (True, False))
    x = torch.randn(5, device=device, requires_grad=mode != "no input requiring grad")
    y = torch.randn(5, device=device)
    if mode == "a non-differentiable input":
        op = _bridge.WarpOp("square_sum", run, (wp.float32, wp.float32), (False, True), (True, False))
    with torch.no_grad() if mode == "no_grad" else torch.enable_grad():
        out, flag = _bridge.apply(op, x, y)
    assert seen == [None]
    assert not out.requires_grad and out.grad_fn is None
    torch.testing.assert_close(out, x.detach() ** 2 + 3 * y)
    assert bool((flag == 1).all())
    taped, _ = _bridge.apply(_op(torch.float32), x.detach().requires_grad_(True), y)
    torch.testing.assert_close(out, taped.detach(), rtol=0, atol=0)


def test_an_untaped_op_inside_a_callers_tape_does_not_record_on_it(device):
    """With a tape of the caller's open, an op no gradient can reach takes the taped path, which refuses the foreign
    tape, instead of recording its launches on it."""
    x = torch.randn(5, device=device)
    with wp.Tape() as tape, torch.no_grad(), pytest.raises(RuntimeError, match="tape"):
        _bridge.apply(_op(torch.float32), x, x)
    assert not tape.launches


@pytest.mark.parametrize("n", [0, 1, 4095, 4096, 100_003])
def test_launch_split_covers_every_item(n):
    """Visit every item exactly once when a launch is split across threads (sizes straddle the chunk)."""
    x = wp.array(np.arange(n, dtype=np.float32), dtype=float, device="cpu")
    out = wp.zeros(n, dtype=float, device="cpu")
    for _ in range(2):  # first call compiles sequentially, second fans out
        out.zero_()
        _bridge.launch_split(_offset_kernel, n, [x], [out], device="cpu", min_chunk=1000)
        np.testing.assert_array_equal(out.numpy(), 2 * np.arange(n, dtype=np.float32))


def test_sort_probe_sorts_on_every_device(device):
    """The probe ``recover_after_oom`` relies on is a real, checked sort (it passes where Warp's sort works)."""
    assert _bridge._sort_works(_bridge.warp_device(device))


def test_recover_after_oom_retries_a_failed_sort_and_then_gives_up(monkeypatch):
    """Warp 1.19's first CUDA radix sort after a failed device allocation returns its keys unsorted
    (measured on an H200, lab/gpu.md): the recovery re-checks until a sort works, raises when none
    does, and does nothing on the CPU (a CUDA device is stood in for: this machine may have none)."""
    from types import SimpleNamespace

    results, calls = [], []

    def probe(wdev):
        calls.append(wdev)
        return results.pop(0)

    monkeypatch.setattr(_bridge, "_sort_works", probe)
    _bridge.recover_after_oom("cpu")
    assert calls == []
    monkeypatch.setattr(_bridge, "warp_device", lambda d: SimpleNamespace(is_cuda=True, name=str(d)))
    results[:] = [False, True]
    _bridge.recover_after_oom("cuda:0")
    assert len(calls) == 2 and results == []
    results[:] = [False] * _bridge._RECOVER_TRIES
    with pytest.raises(RuntimeError, match="still fails after a failed allocation"):
        _bridge.recover_after_oom("cuda:0")
    assert len(calls) == 2 + _bridge._RECOVER_TRIES


@wp.kernel
def _scale_kernel(s: Any, x: wp.array[Any], out: wp.array[Any]):
    i = wp.tid()
    out[i] = s * x[i]


@pytest.mark.parametrize("resolve", [True, False])
def test_launch_resolves_each_argument_types_overload_once_and_computes_as_wp_launch(device, resolve, monkeypatch):
    """``_bridge.launch`` picks the overload ``wp.launch`` would for every argument types (float32 and float64
    arrays, a float32 and a float64 scalar), keeps it per kernel and types (the same object on a second call), records
    on the tape as ``wp.launch`` does, and with ``RESOLVE_OVERLOADS`` off leaves the lookup to Warp."""
    monkeypatch.setattr(_bridge, "RESOLVE_OVERLOADS", resolve)
    picked = []
    for wdt, scalar in ((wp.float32, wp.float32(2.0)), (wp.float64, wp.float64(2.0))):
        x = wp.array(np.arange(5.0), dtype=wdt, device=device, requires_grad=True)
        out = wp.zeros(5, dtype=wdt, device=device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            _bridge.launch(_scale_kernel, 5, [scalar, x], [out], device=device)
        np.testing.assert_array_equal(out.numpy(), 2.0 * np.arange(5.0))
        tape.backward(grads={out: wp.ones(5, dtype=wdt, device=device)})
        np.testing.assert_array_equal(x.grad.numpy(), np.full(5, 2.0))
        k = _bridge.resolve(_scale_kernel, [scalar, x, out])
        picked.append(k)
        if resolve:
            assert not k.is_generic and k is _bridge.resolve(_scale_kernel, [scalar, x, out])
            assert k.adj.arg_types["x"].dtype == wdt and k.adj.arg_types["s"] == wdt
        else:
            assert k is _scale_kernel
    assert (picked[0] is not picked[1]) == resolve  # one overload per float type


def _run_torch_alloc(x, y):
    out = _bridge.empty(x.shape, x.dtype, x.device, requires_grad=True, zero=True)
    flag = _bridge.empty(x.shape, wp.int32, x.device, zero=True)
    wp.launch(_square_sum_kernel, dim=x.shape[0], inputs=[x, y], outputs=[out, flag], device=x.device)
    return out, flag


def test_outputs_in_torch_memory_match_and_are_freed_with_their_graph(device):
    """An op whose outputs :func:`_bridge.empty` allocates gives Warp's own results and gradients, and its outputs
    are freed with their graph by reference counting alone: handing torch the very tensor the context's Warp array
    keeps would tie them in a cycle that is never freed (on an H200 a fit filled the GPU's 140 GB in minutes)."""
    import gc
    import weakref

    x = torch.randn(9, dtype=torch.float64, device=device, requires_grad=True)
    y = torch.randn(9, dtype=torch.float64, device=device, requires_grad=True)
    op = _bridge.WarpOp("square_sum_torch", _run_torch_alloc, (wp.float64, wp.float64), (True, True), (True, False))
    out, flag = _bridge.apply(op, x, y)
    ref, ref_flag = _bridge.apply(_op(torch.float64), x, y)
    assert torch.equal(out, ref) and torch.equal(flag, ref_flag)
    (g,) = torch.autograd.grad(out.sum(), x)
    (g_ref,) = torch.autograd.grad(ref.sum(), x)
    assert torch.equal(g, g_ref)
    assert torch.autograd.gradcheck(lambda a, b: _bridge.apply(op, a, b)[0], (x, y))
    gc.collect()
    gc.disable()
    try:
        out, flag = _bridge.apply(op, x, y)
        out.sum().backward()
        storage = weakref.ref(out._base if out._base is not None else out)
        del out, flag
        assert storage() is None
    finally:
        gc.enable()


def test_to_warp_views_non_contiguous_tensors_by_value(device):
    """An expanded gradient (a sum's), a transposed and a sliced tensor are viewed through a contiguous copy that the
    view keeps alive: the same values, as scalars and as vectors."""
    import gc

    base = torch.arange(24, dtype=torch.float32, device=device).reshape(4, 6)
    cases = [torch.full((), 2.5, device=device).expand(5, 3), base.t(), base[:, ::2]]
    for t in cases:
        assert not t.is_contiguous()
        want = t.cpu().numpy().copy()
        arr = _bridge.to_warp(t)
        del t
        gc.collect()
        np.testing.assert_array_equal(arr.numpy(), want)
    vec = _bridge.to_warp(torch.ones((), device=device).expand(7, 3), wp.vec3)
    assert vec.shape == (7,) and vec.dtype == wp.vec3
    np.testing.assert_array_equal(vec.numpy(), np.ones((7, 3), np.float32))


@pytest.mark.parametrize("dtype,shape,wdt", [(torch.float32, (7, 3), wp.vec3), (torch.float64, (2, 5), wp.float64),
                                             (torch.int32, (11,), wp.int32), (torch.float32, (4, 3, 2), wp.vec2)])
def test_to_warp_view_has_every_attribute_of_warps_constructor(device, dtype, shape, wdt):
    """The direct path's views (:func:`wtopo._views._view`, a template's attributes with the tensor's address) are
    Warp's constructor's arrays attribute for attribute (a Warp upgrade that adds state to arrays fails here), and
    two tensors of one shape get distinct views of their own memory."""
    from wtopo import _views

    a = torch.arange(int(np.prod(shape)), device=device).to(dtype).reshape(shape)
    b = a + 1
    va, vb = _bridge.to_warp(a, wdt), _bridge.to_warp(b, wdt)
    ref = wp.array(ptr=a.data_ptr(), dtype=wdt, shape=va.shape, device=_views._view_device(a.device))
    got, want = dict(vars(va)), dict(vars(ref))
    got.pop("_tensor")
    assert got.keys() == want.keys()
    for k in want:
        if k != "ctype":  # made beforehand here, at the first launch by Warp
            assert got[k] == want[k] if k != "device" else got[k] is want[k], k
    assert va.ptr == a.data_ptr() and vb.ptr == b.data_ptr() and want["ctype"] is None
    assert bytes(va.__ctype__()) == bytes(ref.__ctype__())  # the kernel descriptor a launch passes
    assert bytes(vb.__ctype__()) != bytes(va.__ctype__()) and vb.__ctype__().data == b.data_ptr()
    va.grad = _bridge.to_warp(torch.zeros_like(a), wdt)  # a gradient attached: Warp rebuilds the descriptor
    ref.grad = wp.array(ptr=va.grad.ptr, dtype=wdt, shape=va.shape, device=_views._view_device(a.device))
    assert bytes(va.__ctype__()) == bytes(ref.__ctype__()) and va.__ctype__().grad == va.grad.ptr
    np.testing.assert_array_equal(va.numpy().reshape(-1), a.cpu().numpy().reshape(-1))
    np.testing.assert_array_equal(vb.numpy().reshape(-1), b.cpu().numpy().reshape(-1))


@wp.kernel
def _affine_kernel(a: float, k: int, v: wp.vec2, x: wp.array[float], out: wp.array[float]):
    i = wp.tid()
    out[i] = a * x[i] + float(k) + v[0] * float(i) + v[1]


def test_replayed_launches_set_every_changed_argument_and_dimension(device, monkeypatch):
    """``_bridge.launch`` replays a kept launch command (no tape recording it): every later call with new arrays,
    scalars, a vector and another dimension computes what ``wp.launch`` computes, launches recorded on an active tape
    still go through ``wp.launch`` (so the tape differentiates them), and a command is kept per argument types."""
    monkeypatch.setattr(_bridge, "_commands", {})
    rng = np.random.default_rng(0)
    for n, a, k, v in ((5, 2.0, 1, (0.5, -1.0)), (5, -3.0, 4, (0.0, 2.0)), (9, 0.25, -2, (1.5, 0.5)),
                       (9, 0.25, -2, (1.5, 0.5))):
        x = wp.array(rng.standard_normal(n).astype(np.float32), device=device)
        out = wp.zeros(n, dtype=float, device=device)
        ref = wp.zeros(n, dtype=float, device=device)
        _bridge.launch(_affine_kernel, n, [a, k, wp.vec2(*v), x], [out], device=device, record_tape=False)
        wp.launch(_affine_kernel, n, [a, k, wp.vec2(*v), x], [ref], device=device)
        np.testing.assert_array_equal(out.numpy(), ref.numpy())
    assert len(_bridge._commands) == 1
    x = wp.array(np.arange(4.0, dtype=np.float32), device=device, requires_grad=True)
    out = wp.zeros(4, dtype=float, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        _bridge.launch(_affine_kernel, 4, [3.0, 0, wp.vec2(0.0, 0.0), x], [out], device=device)
    tape.backward(grads={out: wp.ones(4, dtype=float, device=device)})
    np.testing.assert_array_equal(x.grad.numpy(), np.full(4, 3.0))
    assert len(_bridge._commands) == 1


def test_empty_group_carves_aligned_disjoint_arrays_and_zeroed_gradients(device):
    """:func:`_bridge.empty_group` gives one array per type, each of the asked shape at a multiple of 256 bytes into one
    allocation, disjoint from the others (writing one leaves the rest as they were), gradients zeroed and
    likewise disjoint, and outputs that go back to torch as views; mixed scalar types fall back to one each."""
    n = 37
    arrs = _bridge.empty_group(n, (wp.vec3, wp.vec2, wp.float32, wp.vec3), device, requires_grad=True)
    assert [a.shape for a in arrs] == [(n,)] * 4 and [a.dtype for a in arrs] == [wp.vec3, wp.vec2, wp.float32, wp.vec3]
    assert all((a.ptr - arrs[0].ptr) % 256 == 0 and (a.grad.ptr - arrs[0].grad.ptr) % 256 == 0 for a in arrs)
    for k, a in enumerate(arrs):
        _bridge.as_torch(a).fill_(float(k))
        assert torch.count_nonzero(wp.to_torch(a.grad)) == 0
    for k, a in enumerate(arrs):
        assert torch.all(_bridge.as_torch(a) == float(k)), k
    ends = sorted((a.ptr, a.ptr + a.capacity) for a in arrs) + sorted((a.grad.ptr, a.grad.ptr + a.grad.capacity)
                                                                      for a in arrs)
    assert all(e0 <= s1 for (_, e0), (s1, _) in zip(ends[:4], ends[1:4]))
    mixed = _bridge.empty_group((2, 3), (wp.float32, wp.int32), device)
    assert [a.shape for a in mixed] == [(2, 3)] * 2 and mixed[1].dtype == wp.int32


@pytest.mark.parametrize("replay", [True, False])
def test_launch_adjoint_gives_the_tapes_gradients(device, replay, monkeypatch):
    """``_bridge.launch_adjoint`` launches what ``warp.Tape.backward`` launches for a recorded launch: the same input
    gradients, accumulated into the given arrays, with a null adjoint for an input without one, on a second call with
    other arrays and scalars too (the kept command's arguments all set again)."""
    monkeypatch.setattr(_bridge, "REPLAY_LAUNCHES", replay)
    monkeypatch.setattr(_bridge, "_commands", {})
    rng = np.random.default_rng(1)
    for n, a in ((6, 2.0), (9, -0.5)):
        x = wp.array(rng.standard_normal(n).astype(np.float32), device=device, requires_grad=True)
        out = wp.zeros(n, dtype=float, device=device, requires_grad=True)
        seed = wp.array(rng.standard_normal(n).astype(np.float32), device=device)
        tape = wp.Tape()
        with tape:
            wp.launch(_affine_kernel, n, [a, 3, wp.vec2(0.5, 1.0), x], [out], device=device)
        tape.backward(grads={out: seed})
        want = x.grad.numpy().copy()
        gx = wp.zeros(n, dtype=float, device=device)
        _bridge.launch_adjoint(_affine_kernel, n, [a, 3, wp.vec2(0.5, 1.0), x, out], [0.0, 0, wp.vec2(), gx, seed],
                               device=device)
        np.testing.assert_allclose(gx.numpy(), want, rtol=1e-6)
        np.testing.assert_allclose(want, a * seed.numpy(), rtol=1e-6)
        _bridge.launch_adjoint(_affine_kernel, n, [a, 3, wp.vec2(0.5, 1.0), x, out], [0.0, 0, wp.vec2(), None, seed],
                               device=device)  # no gradient wanted for x: a null adjoint, nothing written
        np.testing.assert_allclose(gx.numpy(), want, rtol=1e-6)
