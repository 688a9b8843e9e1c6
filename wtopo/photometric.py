# SPDX-License-Identifier: Apache-2.0
"""Fused photometric loss ``(1 - w) L1 + w (1 - SSIM)`` of one image pair, on CPU and CUDA through Warp.

SSIM uses a separable Gaussian window: the five moments are blurred along rows, then along columns
and turned into the SSIM map in the same pass (kernels in ``kernels/photometric.py``); the adjoint is
the transpose of the two passes. Four launches in all (two forward, two backward), no host
synchronisation, no atomics. Same definition as :func:`wtopo.metrics.ssim` (population moments
over the valid window positions) and :func:`wtopo.fitting.losses.photometric`.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from . import _bridge
from ._validate import require_same_device, require_tensor
from .kernels import photometric as _k

__all__ = ["photometric_loss", "gaussian_window"]

_windows: dict = {}


def gaussian_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    """Normalised 1-D Gaussian window [size] of standard deviation ``sigma`` [pixels], centred (SSIM's window)."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def _window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    """:func:`gaussian_window`, cached per size, sigma, dtype and device (no upload per call)."""
    key = (size, float(sigma), dtype, str(device))
    if key not in _windows:
        _windows[key] = gaussian_window(size, sigma, dtype, device)
    return _windows[key]


def _validate(pred, target, dssim, window, sigma, k1, k2, data_range) -> None:
    require_tensor("pred", pred, ndim=3)
    require_tensor("target", target, shape=tuple(pred.shape))
    if target.dtype != pred.dtype:
        raise TypeError(f"target must have the dtype of pred ({pred.dtype}), got {target.dtype}")
    require_same_device(pred=pred, target=target)
    if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 == 0:
        raise ValueError(f"window must be an odd int >= 1, got {window!r}")
    h, w = pred.shape[:2]
    if h < window or w < window:
        raise ValueError(f"images must be at least {window}x{window}, got {w}x{h}")
    for name, v, lo in (("sigma", sigma, 0.0), ("k1", k1, 0.0), ("k2", k2, 0.0), ("data_range", data_range, 0.0)):
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > lo):
            raise ValueError(f"{name} must be a finite number > {lo}, got {v!r}")
    if not (isinstance(dssim, (int, float)) and not isinstance(dssim, bool) and 0.0 <= dssim <= 1.0):
        raise ValueError(f"dssim must be a number in [0, 1], got {dssim!r}")


def _maps(pred: torch.Tensor, target: torch.Tensor, win: torch.Tensor, c1: float, c2: float):
    """Per-element ``|pred - target|`` [H, W, C] and SSIM map [Hv, Wv, C] (differentiable w.r.t. ``pred``)."""
    s = _bridge.float_dtype(pred)
    v3, v5 = (wp.vec3d, _k.vec5d) if pred.dtype == torch.float64 else (wp.vec3, _k.vec5f)
    k = win.shape[0]

    def run(x, y, window):
        h, w, c = x.shape
        hv, wv = h - k + 1, w - k + 1
        dev = x.device
        rows = _bridge.empty((h, wv, c), v5, dev)
        tape = _bridge.active_tape()  # None: nothing differentiates this call, no gradient arrays
        l1 = _bridge.empty((h, w, c), s, dev, requires_grad=tape is not None)
        ssim = _bridge.empty((hv, wv, c), s, dev, requires_grad=tape is not None)
        partials = _bridge.empty((hv, wv, c), v3, dev)
        _bridge.launch(_k.ssim_rows_kernel, dim=(h, w, c), inputs=[x, y, window], outputs=[rows, l1], device=dev,
                  record_tape=False)
        _bridge.launch(_k.ssim_map_kernel, dim=(hv, wv, c), inputs=[rows, window, s(c1), s(c2)],
                  outputs=[ssim, partials], device=dev, record_tape=False)

        def backward():
            if not x.requires_grad:
                return
            cols = _bridge.empty((h, wv, c), v3, dev)
            _bridge.launch(_k.ssim_adjoint_columns_kernel, dim=(h, wv, c), inputs=[partials, ssim.grad, window],
                      outputs=[cols], device=dev, record_tape=False)
            _bridge.launch(_k.photometric_grad_kernel, dim=(h, w, c), inputs=[x, y, cols, l1.grad, window],
                      outputs=[x.grad], device=dev, record_tape=False)

        if tape is not None:
            tape.record_func(backward, [l1, ssim, *([x] if x.requires_grad else [])])
        return l1, ssim

    op = _bridge.WarpOp("photometric_loss", run, in_dtypes=(None, None, None),
                        differentiable_inputs=(True, False, False), differentiable_outputs=(True, True))
    return _bridge.apply(op, pred, target.detach(), win)


def photometric_loss(pred: torch.Tensor, target: torch.Tensor, *, dssim: float = 0.2, window: int = 11,
                     sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03, data_range: float = 1.0) -> torch.Tensor:
    """``(1 - dssim) * mean|pred - target| + dssim * (1 - SSIM(pred, target))``, fused.

    SSIM as :func:`wtopo.metrics.ssim`: Gaussian window ``window`` x ``window`` of standard deviation
    ``sigma``, population moments over the valid window positions, averaged over pixels and
    channels.

    Args:
        pred: rendered image [H, W, C] (C = 3 for colour), float32 or float64, differentiable.
        target: reference image of the same shape, dtype and device (not differentiated).
        dssim: weight of the D-SSIM term in [0, 1] (3DGS / 2DGS use 0.2).
        window: odd side of the Gaussian window [pixels]; H and W >= window.
        sigma: standard deviation of the window [pixels].
        k1: luminance stabiliser, times ``data_range``.
        k2: contrast stabiliser, times ``data_range``.
        data_range: value range of the images (1 for [0, 1]).

    Returns:
        Scalar tensor of ``pred``'s dtype, differentiable w.r.t. ``pred`` (the gradient of ``|x|`` at 0 is
        0, as torch's).

    Raises:
        TypeError: non-tensors or mismatched dtypes.
        ValueError: wrong shapes, images smaller than the window, invalid window / weights.

    Limitations:
        One image pair per call; ``target`` gets no gradient.

    References:
        Wang, Bovik, Sheikh, Simoncelli, "Image quality assessment: from error visibility to
        structural similarity", IEEE TIP 2004.
    """
    _validate(pred, target, dssim, window, sigma, k1, k2, data_range)
    win = _window(window, sigma, pred.dtype, pred.device)
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    l1, ssim = _maps(pred, target, win, c1, c2)
    return (1.0 - dssim) * l1.mean() + dssim * (1.0 - ssim.mean())
