# SPDX-License-Identifier: Apache-2.0
"""Repeated calls of :func:`wtopo.rasterize.rasterize_surfels` of one shape, replayed on CUDA as CUDA graphs.

A training loop renders the same number of surfels at the same image size with the same settings many times
over, and below about a million surfels the host side of one eager call (binning, two sorts, a dozen launches,
the autograd bridge) takes longer than its kernels (``benchmarks/gpu.md``). After :data:`EAGER_CALLS` exact calls
of one shape, the op (:func:`wtopo.rasterize._graphable.render_tensors`: the clip planes computed on the device,
the sort sized for the largest pair count seen, rounded up to a power of sqrt(2)) is captured with
``torch.cuda.make_graphed_callables``, and later calls of that shape replay it:

* each call still checks its arguments first, with the eager path's one host read;
* after the replay one host read fetches the pair count, its overflow flag and the clip planes: a view with more
  (tile, surfel) pairs than the graph sorts for renders again eagerly (exact; the next capture of that shape is
  sized for it);
* the images and per-surfel outputs are copies of the graph's buffers and the gradients that reach the inputs
  (``means2d`` included) are copies too, so nothing a caller holds changes at the next call;
* a call that no gradient can reach (grad mode off, or no input requiring grad) replays a graph of the forward
  alone (no autograd, no gradient buffers) that reads the caller's surfel tensors where they lie when the calls
  before its capture passed tensors at the same addresses (a loop's parameters updated in place), and otherwise
  copies them into its own buffers; a call whose tensors have moved renders eagerly and the shape is captured
  again, with copies;
* while a differentiable replay's outputs are alive and no backward has run through them, calls of that shape
  render eagerly: another replay would overwrite what that backward reads. A replay is differentiated once: its
  backward graph adds into gradient buffers that only the next forward replay zeroes, so a second backward through
  it (after ``retain_graph=True``) raises instead of returning doubled gradients; render with
  ``RasterConfig(replay=False)`` to differentiate one render twice.

Same values as the eager path (the deferred sort orders the real pairs as the exact one; the device's clip
planes are the host's), checked once per capture: a capture whose first replay's images or gradients differ from
the captured function run eagerly turns replays off for the process, and a replay that raises does too, with a
``RuntimeWarning``; a capture that raises (out of memory, another thread's CUDA call during it) leaves that shape
eager with a warning. At most :data:`KEPT` shapes keep a capture (their memory pools; the least recently used one
is dropped first, and a dropped shape needs twice as many exact calls before its next capture). Replays are used
only on CUDA, with both clip planes defaulted, at least one surfel, outside a profiled section, autocast, inference
mode and a caller's own stream capture. ``RasterConfig(replay=False)`` turns them off.
"""

from __future__ import annotations

import dataclasses
import warnings
import weakref
from collections import OrderedDict
from collections.abc import Callable

import torch

from .._graphs import capture_forward, make_graphed, on_device
from .._profile import in_section
from .._validate import trusted_values
from ._config import RasterConfig, RenderOutput
from ._graphable import Size, check_outputs, check_replay, pair_budget, render_tensors, view_inputs

EAGER_CALLS = 2
"""Exact calls of one shape before it is captured (a shape called once or twice never pays for a capture)."""
KEPT = 3
"""Shapes that keep a capture at once."""
_KNOWN = 64  # shapes whose exact calls are counted (the least recently called is forgotten first)
_WARMUP = 2  # eager runs of the captured function before the capture
_IMAGES = 6  # rgb, alpha, depth, median, normal, distortion
_MAKE = None  # tests: a stand-in of torch.cuda.make_graphed_callables (with it, replays run on any device)
_CAPTURE = None  # tests: a stand-in of the forward's capture in _graphs.capture_forward (likewise)


class _CopyGrads(torch.autograd.Function):
    """The identity on the inputs of a replay; their gradients, which are the graph's buffers, leave as copies.

    While its node is alive and its backward has not run, the replay may still be differentiated
    (:func:`_pending`). Its backward runs once: a second one raises (the replay's gradients would be doubled)."""

    @staticmethod
    def forward(ctx, *xs: torch.Tensor):
        ctx.done = False
        return tuple(x.view_as(x) for x in xs)

    @staticmethod
    def backward(ctx, *grads):
        if ctx.done:
            raise RuntimeError("rasterize_surfels: a render replayed from a CUDA graph can be differentiated once (its "
                               "graph adds into gradient buffers that only its next replay clears); render with "
                               "RasterConfig(replay=False) to differentiate one render twice")
        ctx.done = True
        return tuple(None if g is None else g.clone() for g in grads)


@dataclasses.dataclass
class _Shape:
    """What is known of one shape of call: its exact calls, the most pairs seen and its capture."""

    calls: int = 0
    most_pairs: int = 0
    graphed: Callable | None = None
    background: torch.Tensor | None = None  # the buffer the graph reads the background from
    pending: weakref.ref | None = None  # the last differentiable replay's _CopyGrads node
    replays: int = 0
    needed: int = EAGER_CALLS  # exact calls before a capture (doubled each time the capture is dropped)
    failed: bool = False  # a capture of this shape raised: it stays eager
    layout: tuple | None = None  # a forward-only shape: where its last call's surfel tensors lay (_layout)
    steady: bool = True  # ... and whether every call's lay there (its capture then reads them in place)


def _layout(tensors) -> tuple:
    """Where and how each tensor lies: all that a graph reading them in place depends on."""
    return tuple((t.data_ptr(), t.dtype, tuple(t.shape), t.stride()) for t in tensors)


class _Forward:
    """A capture of the forward alone (a call no gradient can reach) and the buffers it reads.

    ``in_place``: the graph reads the surfel tensors of the capturing call where they lie (none held: a later call
    whose tensors lie exactly there, the same addresses, dtypes, shapes and strides, is what the graph reads), and
    a call with tensors elsewhere gets ``None``; else they are copied into the capture's own buffers at every call.
    The view's tensors are copied in when they are not the ones copied last (those are held, so their memory is
    not reused meanwhile), the background at every call."""

    def __init__(self, fn, inputs: tuple, view: tuple, background: torch.Tensor, *, in_place: bool):
        self.reads = _layout(inputs) if in_place else None
        self.inputs = None if in_place else tuple(t.detach().clone() for t in inputs)
        means = inputs[0]
        self.shift = torch.zeros(means.shape[0], 2, dtype=means.dtype, device=means.device)
        self.view, self.last_view = tuple(v.clone() for v in view), view
        self.background = background
        args = (*(inputs if in_place else self.inputs), self.shift, *self.view)
        self.run, self.outs = capture_forward(fn, args, warmup=_WARMUP, capture=_CAPTURE)

    def __call__(self, inputs: tuple, view: tuple, bg: torch.Tensor) -> tuple | None:
        if self.reads is not None:
            if _layout(inputs) != self.reads:
                return None
        else:
            for buf, t in zip(self.inputs, inputs):
                buf.copy_(t.detach())
        if any(a is not b for a, b in zip(view, self.last_view)):
            for buf, t in zip(self.view, view):
                buf.copy_(t)
            self.last_view = view
        self.background.copy_(bg)
        self.run()
        return self.outs

    def eager_args(self, inputs: tuple, view: tuple) -> tuple:
        """The arguments of the captured function for an eager run on ``inputs`` and ``view``."""
        return (*(t.detach() for t in inputs), torch.zeros_like(self.shift), *view)


_shapes: OrderedDict = OrderedDict()
failure: str | None = None
"""Why replays are off for this process (``None`` while they are on)."""


def render(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
           colors_or_sh: torch.Tensor, camera, sh_degree: int | None, bg: torch.Tensor, config: RasterConfig,
           eager: Callable[[], RenderOutput]) -> RenderOutput:
    """The render of a checked call with both clip planes defaulted: a replay where one serves, else ``eager()``
    (the exact path), counted towards a capture of the call's shape."""
    inputs = (means, quats, scales, opacities, colors_or_sh)
    grad = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
    if (not config.replay or failure is not None or not (means.is_cuda or (_MAKE if grad else _CAPTURE) is not None)
            or means.shape[0] == 0
            or in_section() or torch.is_inference_mode_enabled() or torch.is_autocast_enabled(means.device.type)
            or (means.is_cuda and torch.cuda.is_current_stream_capturing())):
        return eager()
    key = (means.device, means.dtype, means.shape[0], tuple(colors_or_sh.shape), sh_degree, camera.width,
           camera.height, dataclasses.astuple(config), tuple(t.requires_grad for t in inputs) if grad else None)
    shape = _shapes.get(key)
    if shape is None:
        shape = _shapes[key] = _Shape()
        _forget()
    _shapes.move_to_end(key)
    if shape.graphed is not None and not _pending(shape):
        out = (_replay if grad else _replay_forward)(shape, inputs, camera, sh_degree, bg, config)
        if out is not None:
            return out
    if not grad:
        layout = _layout(inputs)
        shape.steady = shape.steady and shape.layout in (None, layout)
        shape.layout = layout
    out = eager()
    shape.calls += 1
    shape.most_pairs = max(shape.most_pairs, out._pairs or 0)  # noqa: SLF001
    if (shape.graphed is None and not shape.failed and shape.calls >= shape.needed and shape.most_pairs > 0
            and failure is None):
        _capture(shape, inputs, camera, sh_degree, bg, config, grad)
    return out


def _pending(shape: _Shape) -> bool:
    """Whether the last differentiable replay of ``shape`` may still be differentiated."""
    node = shape.pending() if shape.pending is not None else None
    return node is not None and not node.done


def _forget() -> None:
    """Forget the least recently called shapes beyond :data:`_KNOWN` (their captures too)."""
    while len(_shapes) > _KNOWN:
        _shapes.popitem(last=False)


def _drop_oldest_capture() -> None:
    """Make room for one more capture: the least recently called captured shape drops its graph."""
    captured = [s for s in _shapes.values() if s.graphed is not None]
    while len(captured) >= KEPT:
        old = captured.pop(0)
        old.graphed = old.background = old.pending = None
        old.calls, old.needed = 0, 2 * old.needed


def _function(size: Size, sh_degree: int | None, background: torch.Tensor, config: RasterConfig, pairs: int):
    def render_op(means, quats, scales, opacities, colors_or_sh, shift, rays, tables, row4, record):
        return render_tensors(means, quats, scales, opacities, colors_or_sh, shift, rays, tables, row4, record,
                              size=size, sh_degree=sh_degree, background=background, config=config, pairs=pairs)

    return render_op


def _capture(shape: _Shape, inputs: tuple, camera, sh_degree, bg: torch.Tensor, config: RasterConfig,
             grad: bool) -> None:
    """Capture the call's shape for the largest pair count seen, checked against the function run eagerly:
    autograd's forward and backward graphs (``grad``), else the forward alone (:class:`_Forward`)."""
    _drop_oldest_capture()
    means = inputs[0]
    background = bg.detach().clone()
    fn = _function(Size(camera.width, camera.height), sh_degree, background, config,
                   pair_budget(shape.most_pairs, config.max_intersections))
    view = view_inputs(camera, means.device, means.dtype, config)
    if grad:  # the screen-space carrier: a zero leaf requiring grad
        args = (*inputs, torch.zeros(means.shape[0], 2, dtype=means.dtype, device=means.device, requires_grad=True),
                *view)
    with on_device(means.device), torch.enable_grad() if grad else torch.no_grad():
        try:
            if grad:
                graphed = make_graphed(fn, args, warmup=_WARMUP, make=_MAKE)
            else:
                graphed = _Forward(fn, inputs, view, background, in_place=shape.steady)
        except Exception as e:  # noqa: BLE001 - this shape stays eager
            shape.failed = True
            warnings.warn(f"wtopo: rasterize_surfels renders this shape ({means.shape[0]} surfels, "
                          f"{camera.width}x{camera.height}) eagerly: its capture raised {type(e).__name__}: {e}",
                          RuntimeWarning, stacklevel=4)
            return
        try:
            with trusted_values():
                if grad:
                    check_replay(graphed, fn, args)
                else:
                    check_outputs(graphed(inputs, view, bg), fn(*graphed.eager_args(inputs, view)))
        except Exception as e:  # noqa: BLE001 - a replay that disagrees leaves every call eager
            _off(f"{type(e).__name__}: {e}")
            return
    shape.graphed, shape.background = graphed, background


def _replay(shape: _Shape, inputs: tuple, camera, sh_degree, bg: torch.Tensor,
            config: RasterConfig) -> RenderOutput | None:
    """One replay of a differentiable capture; ``None`` where the view had more pairs than it sorts for."""
    means = inputs[0]
    n, dtype, device = means.shape[0], means.dtype, means.device
    shift = torch.zeros(n, 2, dtype=dtype, device=device, requires_grad=True)
    ins = list((*inputs, shift))
    wanted = [k for k, t in enumerate(ins) if t.requires_grad]
    copied = _CopyGrads.apply(*(ins[k] for k in wanted))
    node = copied[0].grad_fn
    for k, t in zip(wanted, copied):
        ins[k] = t
    try:
        with on_device(device):
            shape.background.copy_(bg)
            outs = shape.graphed(*ins, *view_inputs(camera, device, dtype, config))
    except Exception as e:  # noqa: BLE001 - a replay that fails leaves this call and the rest eager
        _off(f"a replay failed: {type(e).__name__}: {e}")
        return None
    return _finish(shape, outs, shift, node, config)


def _replay_forward(shape: _Shape, inputs: tuple, camera, sh_degree, bg: torch.Tensor,
                    config: RasterConfig) -> RenderOutput | None:
    """One replay of a forward-only capture; ``None`` where the view had more pairs than it sorts for or the
    surfel tensors no longer lie where the capture reads them (the shape is then captured again, with copies)."""
    means = inputs[0]
    try:
        with on_device(means.device):
            outs = shape.graphed(inputs, view_inputs(camera, means.device, means.dtype, config), bg)
    except Exception as e:  # noqa: BLE001 - a replay that fails leaves this call and the rest eager
        _off(f"a replay failed: {type(e).__name__}: {e}")
        return None
    if outs is None:
        shape.steady = False
        shape.graphed = shape.background = None
        shape.calls = 0
        return None
    return _finish(shape, outs, None, None, config)


def _finish(shape: _Shape, outs: tuple, shift: torch.Tensor | None, node, config: RasterConfig) -> RenderOutput | None:
    """The caller's output from a replay's ``outs`` (copies), after its one host read; ``None`` on an overflow.
    ``shift``: a differentiable replay's screen-space carrier (``None``: the forward alone), ``node`` its
    :class:`_CopyGrads` node."""
    images, (vis, radii, centres, clip, overflow, count) = outs[:_IMAGES], outs[_IMAGES:]
    # one host read: the overflow flag, the pair count and the clip planes
    over, pairs, near, far = torch.stack([overflow.double(), count.double(), clip[0], clip[1]]).tolist()
    if over:
        if pairs <= config.max_intersections:  # more than that: the eager call raises
            shape.most_pairs = max(shape.most_pairs, int(pairs))
        shape.graphed = shape.background = shape.pending = None  # captured again after the eager call
        return None
    if node is not None:
        shape.pending = weakref.ref(node)
    shape.replays += 1
    if shift is None:
        shift = centres.detach().clone()
    else:
        with torch.no_grad():
            shift.copy_(centres)  # the projected centres, as the eager path's means2d (its value is never read)
    rgb, alpha, depth, median, normal, dist = (o.clone() for o in images)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                        visibility=vis.clone(), radii=radii.clone(), means2d=shift,
                        clip=clip.detach().clone(), _host_clip=(near, far), _pairs=int(pairs))


def _off(why: str) -> None:
    global failure
    failure = why
    _shapes.clear()
    warnings.warn(f"wtopo: rasterize_surfels renders eagerly from now on: {why}", RuntimeWarning, stacklevel=4)


def reset() -> None:
    """Forget every shape and capture, and turn replays back on (tests)."""
    global failure
    failure = None
    _shapes.clear()
