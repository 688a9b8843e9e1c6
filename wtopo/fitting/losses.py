# SPDX-License-Identifier: Apache-2.0
"""Loss terms of the fit, pure torch.

Every term is finite for any input the renderers produce: masks are applied before ``log`` (so
invalid pixels get exactly zero gradient), zero vectors are never normalised without an epsilon,
and a term over an empty mask is ``0`` (connected to the graph), never the NaN of an empty mean.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..metrics import ssim
from ..photometric import photometric_loss

__all__ = [
    "masked_mean",
    "l1",
    "photometric",
    "mask_loss",
    "normal_consistency",
    "distortion",
    "scale_regularizer",
    "mesh_depth_loss",
    "mesh_normal_loss",
    "safe_normalize",
]

_NORMAL_EPS = 1e-8  # below this length a normal is treated as absent (zero alpha)
_SSIM_WINDOW = 11  # window of wtopo.metrics.ssim's defaults (smaller images take the torch path and its error)


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` over ``mask`` (same leading shape); ``0`` with the graph kept when empty."""
    m = mask.to(values.dtype)
    while m.ndim < values.ndim:
        m = m.unsqueeze(-1)
    m = m.expand_as(values)
    count = m.sum()
    return (values * m).sum() / count.clamp_min(1.0)


def safe_normalize(v: torch.Tensor, eps: float = _NORMAL_EPS) -> torch.Tensor:
    """``v / |v|`` over the last axis with ``|v|`` clamped to ``eps`` (zero stays zero, finite gradient)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference."""
    return (pred - target).abs().mean()


def photometric(pred: torch.Tensor, target: torch.Tensor, dssim: float) -> torch.Tensor:
    """``(1 - dssim) * L1 + dssim * (1 - SSIM)`` of images [H, W, 3] (SSIM of :func:`wtopo.metrics.ssim`).

    On CUDA the fused Warp loss :func:`wtopo.ops.photometric_loss` (four launches, equal to the torch
    formulation below up to float32 summation order); on the CPU, and for images smaller than the SSIM
    window, the torch formulation: on an idle 2-core CPU it is 3x faster than the fused loss at 128 px
    (4.8 against 15.7 ms forward + backward, ``benchmarks/losses.md``).
    """
    if pred.is_cuda and min(pred.shape[0], pred.shape[1]) >= _SSIM_WINDOW:
        return photometric_loss(pred, target.detach().to(pred.dtype), dssim=dssim)
    loss = (1.0 - dssim) * l1(pred, target)
    if dssim > 0:
        loss = loss + dssim * (1.0 - ssim(pred, target))
    return loss


def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy between rendered opacity [H, W] and an object mask [H, W]: bool, or a
    float target opacity in [0, 1]."""
    a = alpha.clamp(1e-6, 1 - 1e-6)  # BCE is infinite at exactly 0 / 1
    return F.binary_cross_entropy(a, mask.to(alpha.dtype))


def normal_consistency(rendered: torch.Tensor, from_depth: torch.Tensor, alpha: torch.Tensor,
                       mask: torch.Tensor) -> torch.Tensor:
    """Alpha-weighted ``1 - <n_rendered, n_depth>`` over ``mask`` (2DGS).

    ``rendered`` [H, W, 3] is the alpha-weighted rendered normal (its length is about the alpha), so
    ``<rendered, n_depth>`` is weighted by coverage without normalising zero vectors.
    """
    dot = (rendered * from_depth.detach()).sum(-1)
    return masked_mean(alpha.detach() - dot, mask)


def distortion(dist: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of the rendered depth-distortion map [H, W] (over ``mask`` when given)."""
    return dist.mean() if mask is None else masked_mean(dist, mask)


def scale_regularizer(scales: torch.Tensor, max_anisotropy: float) -> torch.Tensor:
    """Scale regulariser of linear scales [N, 2] or [N, 3].

    With three scales: the shortest axis (PGSR's flattening of 3D Gaussians). With two (2D
    surfels, flat by construction): ``relu(max / min - max_anisotropy)``, which stops needles.
    Zero surfels give 0.
    """
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    if scales.shape[-1] == 3:
        return scales.min(dim=-1).values.mean()
    ratio = scales.max(dim=-1).values / scales.min(dim=-1).values.clamp_min(1e-12)
    return F.relu(ratio - max_anisotropy).mean()


def mesh_depth_loss(surfel_depth: torch.Tensor, mesh_depth: torch.Tensor, mask: torch.Tensor, *,
                    eps: float, form: str = "log_ratio", extent: float = 1.0, debias: bool = False) -> torch.Tensor:
    """Agreement of surfel depth and proxy-mesh depth [H, W] on ``mask`` (pixels both cover).

    ``form="log_ratio"``: ``|log d_s - log d_m|``; ``"log1p_abs"``: ``log1p(|d_m - d_s| / extent)``.
    Depths are masked before the ``log`` and clamped to ``eps`` (scene units), so invalid pixels
    have exactly zero gradient. Empty mask -> 0.

    ``debias=True`` subtracts the median over ``mask`` of the difference (``log d_s - log d_m``, or
    ``d_s - d_m``) before the absolute value: a constant offset between the two surfaces in this
    view (the Poisson proxy's smoothing puts it inside the surfels on convex objects) carries no
    loss, and moving every pixel by the same amount gets no gradient; only the difference of their
    shapes does. The median is part of the loss (its gradient reaches the median pixel) and is taken
    without a host read (``nanmedian`` over the masked pixels; 0 when there are none).
    """
    ds = torch.where(mask, surfel_depth, torch.ones_like(surfel_depth)).clamp_min(eps)
    dm = torch.where(mask, mesh_depth, torch.ones_like(mesh_depth)).clamp_min(eps)
    if form == "log_ratio":
        diff = torch.log(ds) - torch.log(dm)
    elif form == "log1p_abs":
        diff = (ds - dm) / extent
    else:
        raise ValueError(f"form must be 'log_ratio' or 'log1p_abs', got {form!r}")
    if debias:
        # pixels off the mask are left out of the median as NaN; their shifted value is masked out below
        diff = diff - torch.nan_to_num(torch.nanmedian(torch.where(mask, diff, torch.full_like(diff, float("nan")))))
    err = diff.abs() if form == "log_ratio" else torch.log1p(diff.abs())
    return masked_mean(err, mask)


def mesh_normal_loss(surfel_normal: torch.Tensor, mesh_normal: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``1 - |<n_surfel, n_mesh>|`` on ``mask``, both [H, W, 3].

    The rendered normal is normalised safely; the absolute value makes the term independent of
    the proxy mesh's orientation (a face seen from behind agrees as well). Empty mask -> 0.
    """
    ns = safe_normalize(torch.where(mask[..., None], surfel_normal, torch.zeros_like(surfel_normal)))
    nm = torch.where(mask[..., None], mesh_normal, torch.zeros_like(mesh_normal))
    dot = (ns * nm).sum(-1).abs()
    return masked_mean(1.0 - dot, mask)
