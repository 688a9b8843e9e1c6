# SPDX-License-Identifier: Apache-2.0
"""Multi-view window cost: the patch NCC of reference windows mapped through their rendered planes into
neighbouring views, on CPU and CUDA through Warp (kernels in ``kernels/multiview_ncc.py``).

For each drawn window (centre pixel ``(py, px)`` of the reference view, ``(2 half + 1)^2`` pixels) the
plane at its centre (rendered z-depth and normal) sends every window pixel's ray into each source view
(the plane-induced homography, evaluated per pixel with the cameras' own rays and projection, so
distortion and skew need no undistortion); the source's grey image is sampled bilinearly there (as
``grid_sample(mode="bilinear", padding_mode="border", align_corners=False)``) and compared with the
reference window by normalised cross-correlation. One launch forward, one backward, no host
synchronisation. This is the scoring of :class:`wtopo.fitting.multiview.MultiViewNCC`; the direct
world-space reference is ``tests/reference/multiview.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
import warp as wp

from . import _bridge
from ._validate import require_tensor, value_checks
from .camera import Camera
from .kernels import multiview_ncc as _k

__all__ = ["ReferenceWindows", "source_params", "window_ncc_costs"]

_MAX_SOURCES = 2  # the kernel scores one or two sources per window (the fit draws two neighbours)
# windows per CPU thread at least: ~1 us per window and source, so a 1,024-window call splits in two while a
# few dozen windows stay one launch (a split costs a thread hand-off, tens of us)
_MIN_CHUNK = 256


class ReferenceWindows(NamedTuple):
    """What the reference view gives every window, whatever plane goes through it (one dtype and device).

    Attributes:
        gray: grey levels ``[H, W]``.
        mean: per pixel, the mean grey level of the window centred there ``[H, W]``.
        var: per pixel, the variance of the grey levels of that window ``[H, W]`` (population).
        dirs: world ray directions through the pixel centres ``[H, W, 3]`` (camera z = 1, as
            :meth:`wtopo.Camera.pixel_rays`); every ray starts at the camera centre.
        length: the rays' lengths ``[H, W]`` (for the grazing test).
    """

    gray: torch.Tensor
    mean: torch.Tensor
    var: torch.Tensor
    dirs: torch.Tensor
    length: torch.Tensor


def source_params(reference: Camera, source: Camera, *, dtype: torch.dtype = torch.float32,
                  device: torch.device | str = "cpu") -> torch.Tensor:
    """One source row ``[23]`` of ``dtype`` on ``device`` for :func:`window_ncc_costs` (layout
    ``kernels/multiview_ncc.py``'s ``PARAMS``). The reference centre is moved into the source's frame in
    ``dtype`` (``R_s c + t_s``), as the rays are."""
    kw = dict(dtype=dtype, device=device)
    R = torch.as_tensor(source.R, **kw)
    o = R @ torch.as_tensor(reference.center, **kw) + torch.as_tensor(source.t, **kw)
    K = source.K
    dist = np.zeros(5) if source.distortion is None else np.asarray(source.distortion, np.float64)
    rest = [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2], *dist, float(source.distortion is not None)]
    return torch.cat([R.reshape(-1), o, torch.as_tensor(np.asarray(rest, np.float64), **kw)])


def _validate(depth, normal, alpha, py, px, reference, images, params, half) -> None:
    require_tensor("depth", depth, ndim=2)
    h, w = depth.shape
    dt, dev = depth.dtype, depth.device
    for name, t, shape in (("normal", normal, (h, w, 3)), ("alpha", alpha, (h, w)),
                           *((f"reference.{k}", getattr(reference, k), (h, w, 3) if k == "dirs" else (h, w))
                             for k in ReferenceWindows._fields)):
        require_tensor(name, t, shape=shape)
        if t.dtype != dt or t.device != dev:
            raise TypeError(f"{name} must be {dt} on {dev} like depth, got {t.dtype} on {t.device}")
    for name, t in (("py", py), ("px", px)):
        require_tensor(name, t, ndim=1, dtypes=(torch.int64,))
        if t.device != dev or t.shape != py.shape:
            raise ValueError(f"{name} must be [{py.shape[0]}] on {dev}, got {list(t.shape)} on {t.device}")
    if not 1 <= len(images) <= _MAX_SOURCES:
        raise ValueError(f"images must hold 1 to {_MAX_SOURCES} source images, got {len(images)}")
    require_tensor("params", params, shape=(len(images), _k.PARAMS))
    for j, img in enumerate(images):
        require_tensor(f"images[{j}]", img, ndim=2)
        if img.dtype != dt or img.device != dev:
            raise TypeError(f"images[{j}] must be {dt} on {dev} like depth, got {img.dtype} on {img.device}")
    if isinstance(half, bool) or not isinstance(half, int) or half < 1 or 2 * half >= min(h, w):
        raise ValueError(f"half must be an int in [1, {(min(h, w) - 1) // 2}] for a {w}x{h} view, got {half!r}")
    if value_checks() and py.numel():
        lo = min(int(py.min()), int(px.min()))  # host sync: validation only
        if lo < half or int(py.max()) >= h - half or int(px.max()) >= w - half:
            raise ValueError(f"py, px must lie at least half = {half} pixels inside the {w}x{h} view")


def window_ncc_costs(depth: torch.Tensor, normal: torch.Tensor, alpha: torch.Tensor, py: torch.Tensor,
                     px: torch.Tensor, reference: ReferenceWindows, images: Sequence[torch.Tensor],
                     params: torch.Tensor, *, half: int, min_std: float, grazing: float, alpha_min: float = 0.5,
                     eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Best ``1 - NCC`` over the sources of the windows centred on ``(py, px)``, and which windows count.

    Args:
        depth: rendered z-depth of the reference view ``[H, W]``, float32 or float64 (differentiable).
        normal: rendered world normal ``[H, W, 3]``, any length (differentiable; normalised here).
        alpha: rendered opacity ``[H, W]`` (value only).
        py: window centre rows ``[P]`` int64, at least ``half`` pixels inside the view; may repeat.
        px: window centre columns ``[P]`` int64, likewise.
        reference: the reference view's :class:`ReferenceWindows` (value only).
        images: the sources' grey images, one or two ``[Hs, Ws]`` (value only).
        params: the sources' rows ``[len(images), 23]`` (:func:`source_params`).
        half: half the window side [pixels].
        min_std: reference windows whose grey-level standard deviation is under this do not count.
        grazing: windows with a ray whose ``|cos|`` to the plane normal is at most this do not count.
        alpha_min: windows whose centre's opacity is under this do not count.
        eps: added under the NCC's square root.

    Returns:
        ``(cost [P], ok [P])`` of ``depth``'s dtype. ``ok`` is 1 where the window counts (positive depth,
        textured, covered, not grazing), else 0, not differentiable. ``cost`` is ``clamp(1 - NCC, 0, 2)`` of
        the best source (2 for a source a window point falls behind or outside of) where the window counts,
        differentiable w.r.t. ``depth`` and ``normal`` (torch's ``amin`` convention: equal costs share the
        gradient); 2 without a gradient where it does not (such windows are not scored).

    Raises:
        TypeError: non-tensors, mismatched dtypes or devices.
        ValueError: wrong shapes, no or more than two sources, ``half`` too large, centres too near the border.

    Limitations:
        One reference view per call; at most two sources; gradients reach only ``depth`` and ``normal``.
    """
    _validate(depth, normal, alpha, py, px, reference, images, params, half)
    s = _bridge.float_dtype(depth)
    v3, v4 = (wp.vec3d, wp.vec4d) if depth.dtype == torch.float64 else (wp.vec3, wp.vec4)
    forward_kernel, adjoint_kernel, scatter_kernel = _k.OVERLOADS[s]
    sources = len(images)
    img1 = images[1] if sources > 1 else images[0]

    def run(d, n, a, yy, xx, gray, mean, var, dirs, length, im0, im1, prm):
        dev = d.device
        count = yy.shape[0]
        tape = _bridge.active_tape()  # None: nothing differentiates this call, no gradient array
        cost = _bridge.empty(count, s, dev, requires_grad=tape is not None)
        ok = _bridge.empty(count, s, dev)
        stats = _bridge.empty((count, _MAX_SOURCES), v4, dev)
        _bridge.launch_split(forward_kernel, count, [d, n, a, yy, xx, gray, mean, var, dirs, length, im0, im1, prm,
                                                     sources, int(half), s(min_std), s(grazing), s(alpha_min), s(eps)],
                             [cost, ok, stats], device=dev, min_chunk=_MIN_CHUNK)

        def backward():
            if not (d.requires_grad or n.requires_grad):
                return
            gd = d.grad if d.requires_grad else _bridge.empty(d.shape, s, dev, zero=True)
            gn = n.grad if n.requires_grad else _bridge.empty(n.shape, v3, dev, zero=True)
            gwd = _bridge.empty(count, s, dev)
            gwn = _bridge.empty(count, v3, dev)
            _bridge.launch_split(adjoint_kernel, count, [d, n, yy, xx, gray, mean, var, dirs, im0, im1, prm, sources,
                                                         int(half), stats, cost.grad], [gwd, gwn], device=dev,
                                 min_chunk=_MIN_CHUNK)
            _bridge.launch(scatter_kernel, dim=count, inputs=[yy, xx, gwd, gwn], outputs=[gd, gn], device=dev,
                      record_tape=False)

        if tape is not None:
            tape.record_func(backward, [cost, *([d] if d.requires_grad else []), *([n] if n.requires_grad else [])])
        return cost, ok

    op = _bridge.WarpOp("window_ncc_costs", run,
                        in_dtypes=(None, v3, None, wp.int64, wp.int64, None, None, None, v3, None, None, None, None),
                        differentiable_inputs=(True, True, *([False] * 11)),
                        differentiable_outputs=(True, False))
    return _bridge.apply(op, depth, normal, alpha.detach(), py, px, *(t.detach() for t in reference),
                         images[0].detach(), img1.detach(), params.detach())
