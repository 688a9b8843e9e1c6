# SPDX-License-Identifier: Apache-2.0
"""The one torch <-> Warp bridge every differentiable op goes through.

An op describes itself as a :class:`WarpOp`: a ``run`` callable that takes Warp views of the
input tensors and returns Warp output arrays, recording its launches on the active
:class:`warp.Tape` (plain ``wp.launch`` calls are recorded automatically; ops with explicit adjoint
kernels register them with :meth:`warp.Tape.record_func`). :func:`apply` wraps that in a
``torch.autograd.Function`` (where no gradient can flow, :func:`apply` runs ``run`` with no tape and returns plain
tensors):

* forward: tensors are made contiguous and viewed as Warp arrays without a copy (inputs that
  require grad get a zeroed gradient buffer owned by torch, which Warp views), launches run on the
  tensors' device and, on CUDA, on torch's current stream;
* backward: the upstream gradients are copied into the outputs' gradient buffers (Warp's adjoints
  may clear what they read, so torch's own tensors are never handed to them), the tape is replayed
  backwards and the input gradient buffers go back to torch as they are. Differentiating the same
  graph again (``retain_graph``, ``torch.autograd.gradcheck``) gives the inputs fresh buffers and
  zeroes every other buffer the tape wrote, never one already handed to torch.

Outputs flagged non-differentiable (indices, masks, counts) are marked so with
``ctx.mark_non_differentiable`` and never receive a gradient.

The hot ops allocate their arrays with :func:`empty` (``wtopo._views``): torch's caching allocator owns the memory
and an output goes back to torch as a view of its tensor, with no conversion; :func:`to_warp` views a tensor
directly at its address (a fifth of the host time of the view through ``wp.from_torch`` it replaces,
``benchmarks/gpu.md``).

:func:`launch` is ``wp.launch`` with a generic kernel's overload resolved once per argument types (Warp
infers it at every launch otherwise: a third of a small render's host time). :func:`launch_split` runs a
kernel whose threads write disjoint outputs in several chunks from Python threads: Warp's CPU backend runs
each launch on one thread but releases the GIL, so on a 2-core CPU this gives about 2x (measured,
``design/overview.md``). On CUDA it is a single launch.
"""

from __future__ import annotations

import ctypes
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from ._streams import _on_torch_stream, _warp_stream, registered_capture, torch_stream  # noqa: F401 - re-exported
from ._views import (
    _ensure_init,
    as_torch,
    empty,
    empty_group,
    empty_struct,
    float_dtype,
    quad_view,
    struct_view,
    to_warp,
    vec_dtype,
)

__all__ = [
    "WarpOp",
    "apply",
    "active_tape",
    "warp_device",
    "to_warp",
    "empty",
    "empty_group",
    "struct_view",
    "empty_struct",
    "quad_view",
    "registered_capture",
    "as_torch",
    "launch",
    "launch_adjoint",
    "launch_split",
    "cpu_threads",
    "float_dtype",
    "vec_dtype",
    "torch_stream",
    "recover_after_oom",
]

_pools_kept: set = set()
_POOL_KEEP_BYTES = 4 << 30  # at most this much freed memory stays cached in a CUDA device's pool
_POOL_KEEP_FRACTION = 0.25  # ... and at most this fraction of the device's memory


def _keep_pool(wdev) -> None:
    """Let a CUDA device's stream-ordered memory pool keep freed memory.

    Warp allocates with ``cudaMallocAsync``; the pool's default release threshold (0) hands freed
    memory back to the driver at every synchronisation, so the next allocation maps it again
    (measured ~20 us per ``cudaMallocAsync``, ~50 per 256^3 proxy-mesh step on an H200). A
    threshold the user already set is left alone.
    """
    _pools_kept.add(wdev.ordinal)
    if not wdev.is_mempool_enabled or wp.get_mempool_release_threshold(wdev) != 0:
        return
    wp.set_mempool_release_threshold(wdev, int(min(_POOL_KEEP_BYTES, _POOL_KEEP_FRACTION * wdev.total_memory)))


def warp_device(device: torch.device | str) -> wp.context.Device:
    """Return the Warp device matching a torch device (``cpu`` or ``cuda:N``)."""
    _ensure_init()
    wdev = wp.device_from_torch(torch.device(device))
    if wdev.is_cuda and wdev.ordinal not in _pools_kept:
        _keep_pool(wdev)
    return wdev


def _sort_works(wdev) -> bool:
    """Whether Warp's radix sort sorts two pairs on ``wdev`` (one host sync)."""
    keys = wp.array(np.array([1, 0, 0, 0], dtype=np.int32), dtype=wp.int32, device=wdev)
    values = wp.array(np.array([0, 1, 0, 0], dtype=np.int32), dtype=wp.int32, device=wdev)
    wp.utils.radix_sort_pairs(keys, values, 2)
    return keys.numpy()[:2].tolist() == [0, 1] and values.numpy()[:2].tolist() == [1, 0]


_RECOVER_TRIES = 3


def recover_after_oom(device: torch.device | str) -> None:
    """Put Warp's radix sort on ``device`` back in order after a Warp allocation there failed.

    With Warp 1.19, the first radix sort on a CUDA device after ``wp_alloc_device_async`` ran out of
    memory fails inside CUB (``invalid device ordinal`` while sizing its buffer) and returns its keys
    unsorted, saying so only on stderr; the next sort works (measured on an H200). Every surfel render sorts,
    so a fit that goes on after such a failure (the
    final re-mesh's fallback to the CPU) would composite one image out of depth order. A checked sort
    of two pairs takes that failure instead; raises ``RuntimeError`` when the sort still fails after
    three tries. A no-op on the CPU.
    """
    wdev = warp_device(device)
    if not wdev.is_cuda:
        return
    for _ in range(_RECOVER_TRIES):
        if _sort_works(wdev):
            return
    raise RuntimeError(f"Warp's radix sort on {wdev} still fails after a failed allocation there "
                       f"({_RECOVER_TRIES} checked tries); restart the process")


def _grad_buffer(arr: wp.array, like: torch.Tensor) -> torch.Tensor:
    """Attach a zeroed gradient buffer owned by torch, of ``like``'s shape and dtype, to ``arr`` and return it.

    Warp views it without a copy, so backward hands it to torch as it is (no clone, no ``tape.zero()``).
    """
    g = torch.zeros(like.shape, dtype=like.dtype, device=like.device)
    arr.grad = to_warp(g, arr.dtype)
    return g


@dataclass(frozen=True)
class WarpOp:
    """What the bridge needs to run one differentiable op.

    Args:
        name: op name used in error messages.
        run: ``run(*warp_inputs) -> tuple[wp.array, ...]``; called on the inputs' device inside an active
            :class:`warp.Tape` where a gradient can flow, else with none (:func:`active_tape` is ``None``; the
            outputs then need no gradient arrays). Differentiable outputs of a taped run must be allocated with
            ``requires_grad=True``.
        in_dtypes: Warp dtype per input tensor (``None`` keeps the tensor's scalar dtype).
        differentiable_inputs: per input, whether a gradient may flow into it.
        differentiable_outputs: per output, whether it carries a gradient.
    """

    name: str
    run: Callable[..., tuple]
    in_dtypes: Sequence
    differentiable_inputs: Sequence[bool]
    differentiable_outputs: Sequence[bool]
    extra: dict = field(default_factory=dict)


def _ran(op: WarpOp, outs) -> tuple:
    """``op.run``'s outputs, checked to be as many as ``op`` declares."""
    if len(outs) != len(op.differentiable_outputs):
        raise RuntimeError(f"{op.name}: run returned {len(outs)} outputs, expected {len(op.differentiable_outputs)}")
    return outs


class _WarpFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, op: WarpOp, *tensors):
        device = next(t.device for t in tensors if isinstance(t, torch.Tensor))
        wdev = warp_device(device)
        tape = wp.Tape()
        # All Warp work (gradient-buffer zeroing included) on torch's current stream, so it is
        # ordered with the torch ops around it.
        with _on_torch_stream(wdev, device):
            wp_inputs, in_grads = [], []
            for t, dt, diff in zip(tensors, op.in_dtypes, op.differentiable_inputs):
                if not isinstance(t, torch.Tensor):
                    wp_inputs.append(t)
                    continue
                arr = to_warp(t, dt)
                if diff and t.requires_grad:
                    # the input's gradient lives in a torch tensor that backward hands to torch as it is
                    in_grads.append([arr, _grad_buffer(arr, t)])
                wp_inputs.append(arr)
            with tape:
                outs = _ran(op, op.run(*wp_inputs))
        torch_outs = []
        for o, diff in zip(outs, op.differentiable_outputs):
            if diff and o.grad is None:
                raise RuntimeError(f"{op.name}: differentiable output allocated without requires_grad")
            torch_outs.append(as_torch(o))
        ctx.op = op
        ctx.tape = tape
        ctx.wp_inputs = wp_inputs
        ctx.wp_outputs = outs
        ctx.in_grads = in_grads  # [warp input, the torch gradient its .grad views]
        ctx.handed = set()  # addresses of the input gradients backward has handed to torch (never written again)
        ctx.wdev = wdev
        ctx.torch_device = device
        ctx.save_for_backward(*[t for t in tensors if isinstance(t, torch.Tensor)])
        nondiff = [t for t, d in zip(torch_outs, op.differentiable_outputs) if not d]
        if nondiff:
            ctx.mark_non_differentiable(*nondiff)
        return tuple(torch_outs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        op: WarpOp = ctx.op
        _ = ctx.saved_tensors  # torch's in-place modification check
        seeds = {}
        for o, g, diff in zip(ctx.wp_outputs, grads, op.differentiable_outputs):
            if not diff or g is None:
                continue
            seeds[o] = to_warp(g, o.dtype)
        # Everything below runs on torch's current stream: Warp's own CUDA streams do not order
        # against it, so a copy or zero issued outside this scope could read or clear the
        # gradients while the backward kernels are still running (seen on an H200 as partially
        # accumulated gradients).
        with _on_torch_stream(ctx.wdev, ctx.torch_device), registered_capture(ctx.torch_device):
            if ctx.handed:
                # a second backward of the same graph (retain_graph, gradcheck): fresh input gradients, and every
                # other gradient buffer the first one wrote zeroed; never a buffer already handed to torch, which
                # may now be a parameter's .grad
                for entry in ctx.in_grads:
                    entry[1] = _grad_buffer(*entry)
                for g in ctx.tape.gradients.values():
                    if isinstance(g, wp.array) and g.ptr not in ctx.handed:
                        g.zero_()
            if seeds:
                ctx.tape.backward(grads=seeds)
            grads_of = {id(a): g for a, g in ctx.in_grads}
            result: list = [None]
            for a in ctx.wp_inputs:
                g = grads_of.get(id(a)) if seeds else None
                result.append(g)
                if g is not None:
                    ctx.handed.add(g.data_ptr())
        return tuple(result)


def active_tape() -> wp.Tape | None:
    """The tape the bridge is recording on (``None`` outside :func:`apply`).

    Ops with explicit adjoint kernels register them on it with :meth:`warp.Tape.record_func`.
    Warp keeps the active tape only in a private attribute; this is the one place that reads it.
    """
    return wp._src.context.runtime.tape  # noqa: SLF001


def apply(op: WarpOp, *tensors) -> tuple[torch.Tensor, ...]:
    """Run ``op`` on torch tensors and return torch outputs that carry gradients as declared.

    Where no gradient can flow (grad mode off, or no differentiable input requires grad) the op runs with no tape
    active: :func:`active_tape` is ``None``, so it records no adjoint and need not allocate gradient arrays. A tape
    already active (a caller's own, or another thread's op: Warp keeps one per process) takes the taped path, which
    refuses it, rather than having this op's launches recorded on it."""
    if len(tensors) != len(op.in_dtypes):
        raise RuntimeError(f"{op.name}: got {len(tensors)} inputs, expected {len(op.in_dtypes)}")
    if active_tape() is not None or (torch.is_grad_enabled() and any(
            isinstance(t, torch.Tensor) and d and t.requires_grad for t, d in zip(tensors, op.differentiable_inputs))):
        return _WarpFunction.apply(op, *tensors)
    device = next(t.device for t in tensors if isinstance(t, torch.Tensor))
    wdev = warp_device(device)
    with _on_torch_stream(wdev, device):
        outs = op.run(*(to_warp(t, dt) if isinstance(t, torch.Tensor) else t for t, dt in zip(tensors, op.in_dtypes)))
    return tuple(as_torch(o) for o in _ran(op, outs))


def cpu_threads() -> int:
    """Number of Python threads CPU launches are split across (``WTOPO_NUM_THREADS`` or all cores)."""
    env = os.environ.get("WTOPO_NUM_THREADS")
    if env:
        return max(1, int(env))
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


_pool: ThreadPoolExecutor | None = None
_loaded: set = set()


def _get_pool(n: int) -> ThreadPoolExecutor:
    global _pool
    if _pool is None or _pool._max_workers < n:  # noqa: SLF001 - resize only when asked for more threads
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="wtopo-launch")
    return _pool


_overloads: dict = {}
# False: :func:`launch` leaves the overload lookup to Warp at every launch (kept for comparison in benchmarks)
RESOLVE_OVERLOADS = True
# False: :func:`launch` calls ``wp.launch`` every time instead of replaying a kept launch command (for comparison)
REPLAY_LAUNCHES = True
_commands: dict = {}
_COMMANDS_MAX = 4096  # kept launch commands (kernel, device, thread, argument types); cleared when full
_SCALARS = (int, float)
_REPLAY_KWARGS = frozenset({"device", "record_tape"})  # the options a replayed launch takes


def _arg_key(a) -> object:
    # what Warp's overload inference reads of an argument: an array's class, dtype and rank, else the value's type
    dt = getattr(a, "dtype", None)
    return type(a) if dt is None else (type(a), dt, getattr(a, "ndim", None))


def resolve(kernel, args: Sequence) -> wp.Kernel:
    """The overload of ``kernel`` that ``wp.launch`` would pick for ``args`` (inputs then outputs), looked up once
    per kernel and argument types; a kernel that is not generic is returned as it is."""
    if not (RESOLVE_OVERLOADS and kernel.is_generic):
        return kernel
    key = (kernel, *map(_arg_key, args))
    k = _overloads.get(key)
    if k is None:
        k = kernel.add_overload(kernel.infer_argument_types(list(args)))
        _overloads[key] = k
    return k


def _replay(kernel, dim, args: list, device, adj_args: list | None = None) -> None:
    """Launch ``kernel`` on ``args`` by replaying the launch command kept for its argument types on this device and
    thread (:class:`warp.Launch`), with only the changed dimensions and arguments set.

    The first launch of a kernel for some argument types goes through ``wp.launch`` (its checks, its overload, its
    module load) and keeps the command. Later ones set each array argument from its cached descriptor and each
    ``int`` or ``float`` in place; other values (vectors, structs) go through Warp's packing. The argument types
    are part of the key, so every later launch passes the checks the first one passed. About a third of the host
    time of ``wp.launch`` (``lab/host_raster.py``); the kernels and their arguments are the same.
    """
    device = wp.get_device(device)
    adjoint = adj_args is not None
    key = (kernel, device.alias, threading.get_ident(), adjoint, *map(_arg_key, args))
    cmd = _commands.get(key)
    if cmd is None:
        if len(_commands) >= _COMMANDS_MAX:
            _commands.clear()
        k = resolve(kernel, args)
        cmd = wp.launch(k, dim=dim, inputs=args, adj_inputs=adj_args or [], adjoint=adjoint, device=device,
                        record_tape=False, record_cmd=True)
        if cmd is None:  # no module to run (an empty launch): nothing to keep
            return
        cmd.fwd_args = cmd.adj_args = None  # kept for Warp's CPU graph capture only; they keep the last arguments alive
        cmd._wtopo_dim = dim  # noqa: SLF001
        _commands[key] = cmd
        cmd.launch()
        return
    if dim != cmd._wtopo_dim:  # noqa: SLF001
        cmd.set_dim(dim)
        cmd._wtopo_dim = dim  # noqa: SLF001
    params, addr = cmd.params, cmd.params_addr
    n = len(args)
    for i, a in enumerate(args if not adjoint else [*args, *adj_args], 1):
        if type(a) is wp.array:
            c = a.ctype or a.__ctype__()
            if params[i] is not c:
                params[i] = c
                if addr:
                    addr[i] = ctypes.c_void_p(ctypes.addressof(c))
        elif type(a) in _SCALARS:
            params[i].__init__(a)
        elif i <= n:
            cmd.set_param_at_index(i - 1, a)
        else:  # the adjoint half: a null array (None), a struct's or vector's adjoint
            cmd.set_param_at_index(i - 1 - n, a, adjoint=True)
    cmd.launch()


def launch_adjoint(kernel, dim, args: Sequence, adj_args: Sequence, *, device) -> None:
    """The adjoint of ``kernel`` (Warp autodiff) over ``dim`` threads: ``args`` its arguments as the forward launch
    had them (inputs then outputs), ``adj_args`` their adjoints in the same order (an array's gradient or ``None``,
    a zero record for a struct, 0 for an int). What ``warp.Tape.backward`` launches for a recorded launch, from a
    kept launch command (:func:`_replay`) and without the tape's bookkeeping; for ops that register it with
    :meth:`warp.Tape.record_func`."""
    args, adj_args = list(args), list(adj_args)
    if len(adj_args) != len(args):
        raise RuntimeError(f"launch_adjoint: {len(args)} arguments but {len(adj_args)} adjoints")
    if REPLAY_LAUNCHES:
        _replay(kernel, dim, args, device, adj_args)
        return
    wp.launch(resolve(kernel, args), dim=dim, inputs=args, adj_inputs=adj_args, adjoint=True, device=device,
              record_tape=False)


def launch(kernel, dim, inputs: Sequence = (), outputs: Sequence = (), **kwargs) -> None:
    """``wp.launch(kernel, dim, inputs, outputs, **kwargs)`` with a generic kernel's overload resolved by
    :func:`resolve` (same kernel, same results; what changes is the host time of the launch). A launch that no
    tape records (``record_tape=False`` or no active tape) with no option but ``device`` replays a kept launch
    command (:func:`_replay`)."""
    if (REPLAY_LAUNCHES and kwargs.keys() <= _REPLAY_KWARGS
            and (not kwargs.get("record_tape", True) or active_tape() is None)):
        _replay(kernel, dim, [*inputs, *outputs], kwargs.get("device"))
        return
    wp.launch(resolve(kernel, (*inputs, *outputs)), dim=dim, inputs=inputs, outputs=outputs, **kwargs)


def launch_split(kernel, dim: int, inputs: list, outputs: list | None = None, *, device, min_chunk: int = 4096,
                 record_tape: bool = False) -> None:
    """Launch ``kernel`` over ``dim`` threads, split into chunks across CPU threads.

    The kernel's first parameter must be ``offset: int``; thread ``tid`` handles item
    ``offset + tid``. Its threads must write disjoint outputs (Warp's CPU ``atomic_add`` is not
    atomic across concurrent launches). On CUDA, or when ``dim`` is small, this is one launch.
    ``record_tape=False`` keeps the chunks off any active tape: callers register explicit adjoints.
    """
    outputs = outputs or []
    device = wp.get_device(device)
    if dim <= 0:
        return
    n = cpu_threads() if device.is_cpu else 1
    n = int(min(n, max(1, dim // max(1, min_chunk))))
    if n <= 1:
        launch(kernel, dim, [0, *inputs], outputs, device=device, record_tape=record_tape)
        return
    kernel = resolve(kernel, (0, *inputs, *outputs))
    bounds = np.linspace(0, dim, n + 1).astype(np.int64)

    def _run(i):
        lo, hi = int(bounds[i]), int(bounds[i + 1])
        if hi > lo:
            wp.launch(kernel, dim=hi - lo, inputs=[lo, *inputs], outputs=outputs, device=device,
                      record_tape=record_tape)

    # The first launch of a kernel (per device and argument types) compiles it, and generic
    # kernels add overloads on the fly: run that one sequentially so threads never race on a build.
    key = (kernel.key, str(device), tuple(getattr(a, "dtype", type(a)) for a in (*inputs, *outputs)))
    if key not in _loaded:
        for i in range(n):
            _run(i)
        _loaded.add(key)
        return
    futures = [_get_pool(n).submit(_run, i) for i in range(n)]
    for f in futures:
        f.result()
