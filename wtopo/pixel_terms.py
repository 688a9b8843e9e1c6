# SPDX-License-Identifier: Apache-2.0
"""The fit's per-pixel normal, distortion and mask terms in one Warp pass (``kernels/pixel_terms.py``).

One launch forward (the depth normals of the median depth computed on the way, the four partial sums per run of
pixels) and one backward, where the torch formulation they replace (:func:`wtopo.depth_normals.depth_normals`,
:func:`wtopo.fitting.losses.normal_consistency`, :func:`~wtopo.fitting.losses.distortion` and
:func:`~wtopo.fitting.losses.mask_loss`) took one launch and about forty torch operations, forward and backward.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import warp as wp

from . import _bridge
from ._validate import require_finite, require_positive, require_same_device, require_tensor, value_checks
from .kernels import pixel_terms as _k

__all__ = ["pixel_terms", "PixelTerms"]

_RUN_CPU = 64  # pixels of a row per forward thread (one partial sum each): a CPU thread costs about a pixel
_RUN_CUDA = 16  # ... on CUDA: 30k threads at 800 x 600, each still summing a run
_MIN_CHUNK = 1024  # runs per CPU launch thread at least: below, a thread pool costs more than it saves (128 px)


class PixelTerms(NamedTuple):
    """The three terms, scalar tensors of the maps' dtype.

    Attributes:
        normal: ``mean(alpha - <n_rendered, n_depth>)`` over the pixels with a depth normal (2DGS's normal
            consistency; 0 when there is none).
        distortion: the mean of the distortion map.
        mask: the mean binary cross-entropy of the clamped opacity against the target (``None`` without one).
    """

    normal: torch.Tensor
    distortion: torch.Tensor
    mask: torch.Tensor | None


def pixel_terms(normal: torch.Tensor, alpha: torch.Tensor, median_depth: torch.Tensor, distortion: torch.Tensor,
                origins: torch.Tensor, directions: torch.Tensor, valid: torch.Tensor,
                target: torch.Tensor | None = None, *, eps: float = 1e-8, clamp: float = 1e-6) -> PixelTerms:
    """The normal, distortion and mask terms of one rendered view, fused.

    Args:
        normal: rendered normal [H, W, 3], float32 or float64, alpha-weighted (its length is about the opacity),
            world frame; differentiable.
        alpha: rendered opacity [H, W], same dtype; differentiable through the mask term only (the normal term
            holds it fixed, as :func:`wtopo.fitting.losses.normal_consistency`).
        median_depth: rendered median z-depth [H, W], world units; not differentiated (the depth normal is the
            normal term's fixed target).
        distortion: rendered depth-distortion map [H, W]; differentiable.
        origins: ray origins [H, W, 3] (:meth:`wtopo.Camera.pixel_rays`), same dtype.
        directions: ray directions [H, W, 3] with camera-z component 1, same dtype.
        valid: bool [H, W], the pixels whose depth counts for the depth normals (the fit: opacity >= 0.5).
        target: object mask [H, W], bool or the maps' float dtype in [0, 1] (target opacity); ``None``: no mask
            term.
        eps: length of the depth normals' cross product [world units^2] at or below which a pixel has none.
        clamp: the opacity is clamped to ``[clamp, 1 - clamp]`` inside the cross-entropy (its gradient is zero
            outside), in (0, 0.5).

    Returns:
        :class:`PixelTerms`, each term of the maps' dtype on their device; the gradients reach ``normal``,
        ``alpha`` (mask term) and ``distortion``.

    Raises:
        TypeError, ValueError: wrong types, dtypes, shapes or devices; non-finite maps (outside the fit's
            trusted section); ``eps`` < 0 or ``clamp`` outside (0, 0.5).
    """
    require_tensor("alpha", alpha, ndim=2)
    h, w = alpha.shape
    dt = alpha.dtype
    for name, t, shape in (("normal", normal, (h, w, 3)), ("median_depth", median_depth, (h, w)),
                           ("distortion", distortion, (h, w)), ("origins", origins, (h, w, 3)),
                           ("directions", directions, (h, w, 3))):
        require_tensor(name, t, shape=shape, dtypes=(dt,))
    require_tensor("valid", valid, shape=(h, w), dtypes=(torch.bool,))
    if target is not None:
        require_tensor("target", target, shape=(h, w), dtypes=(torch.bool, dt))
    require_same_device(normal=normal, alpha=alpha, median_depth=median_depth, distortion=distortion,
                                 origins=origins, directions=directions, valid=valid, target=target)
    require_positive("eps", eps, allow_zero=True)
    if not (isinstance(clamp, float | int) and not isinstance(clamp, bool) and 0.0 < clamp < 0.5):
        raise ValueError(f"clamp must be a number in (0, 0.5), got {clamp!r}")
    if value_checks():
        for name, t in (("normal", normal), ("alpha", alpha), ("median_depth", median_depth),
                        ("distortion", distortion), ("origins", origins), ("directions", directions)):
            require_finite(name, t.detach())
    has_target = target is not None
    tgt = (target.to(dt) if target.dtype == torch.bool else target.detach()) if has_target else alpha.new_zeros(0, 0)
    if h == 0 or w == 0:
        zero = (normal.sum() + alpha.sum() + distortion.sum()) * 0.0  # connected to the graph
        return PixelTerms(zero, zero, zero if has_target else None)
    s = _bridge.float_dtype(alpha)
    v3 = _bridge.vec_dtype(normal)
    run_px = _RUN_CUDA if alpha.is_cuda else _RUN_CPU
    n_runs = h * -(-w // run_px)

    def run(n_wp, a_wp, d_wp, dist_wp, o_wp, r_wp, valid_wp, t_wp):
        dev = a_wp.device
        sums = wp.empty((n_runs, 4), dtype=s, device=dev, requires_grad=True)
        dn = wp.empty((h, w), dtype=v3, device=dev)
        lo, hi = s(clamp), s(1.0 - clamp)
        _bridge.launch_split(_k.pixel_terms_kernel, n_runs,
                             [n_wp, a_wp, d_wp, dist_wp, o_wp, r_wp, valid_wp, t_wp, int(has_target), lo, hi, s(eps),
                              run_px], [sums, dn], device=dev, min_chunk=_MIN_CHUNK)

        def backward():
            wants = [int(a.requires_grad) for a in (n_wp, a_wp, dist_wp)]
            grads = [a.grad if a.requires_grad else wp.empty((0, 0), dtype=t, device=dev)
                     for a, t in ((n_wp, v3), (a_wp, s), (dist_wp, s))]
            _bridge.launch_split(_k.pixel_terms_backward_kernel, n_runs,
                                 [a_wp, t_wp, dn, sums.grad, int(has_target), lo, hi, run_px, *wants], grads,
                                 device=dev, min_chunk=_MIN_CHUNK)

        tape = _bridge.active_tape()
        if tape is not None:
            tape.record_func(backward, [sums, *(a for a in (n_wp, a_wp, dist_wp) if a.requires_grad)])
        return (sums,)

    op = _bridge.WarpOp("pixel_terms", run, in_dtypes=(v3, None, None, None, v3, v3, wp.uint8, None),
                        differentiable_inputs=(True, True, False, True, False, False, False, False),
                        differentiable_outputs=(True,))
    (sums,) = _bridge.apply(op, normal, alpha, median_depth.detach(), distortion, origins, directions,
                            valid.view(torch.uint8), tgt)
    tot = sums.sum(0)
    pixels = float(h * w)
    return PixelTerms(tot[0] / tot[1].detach().clamp_min(1.0), tot[2] / pixels, tot[3] / pixels if has_target else None)
