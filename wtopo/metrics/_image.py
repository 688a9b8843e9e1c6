# SPDX-License-Identifier: Apache-2.0
"""Image metrics in torch (differentiable): PSNR and SSIM."""

from __future__ import annotations

import torch

from ..photometric import gaussian_window as _gaussian_window


def _image_pair(pred, target):
    for nm, x in (("pred", pred), ("target", target)):
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{nm} must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim not in (3, 4) or x.shape[-1] != 3:
            raise ValueError(f"{nm} must have shape [H, W, 3] or [N, H, W, 3], got {list(x.shape)}")
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {list(pred.shape)} and {list(target.shape)}")
    if pred.ndim == 3:
        pred, target = pred[None], target[None]
    return pred, target.to(pred.dtype)


def psnr(pred: torch.Tensor, target: torch.Tensor, *, mask: torch.Tensor | None = None,
         max_val: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB, averaged over images.

    Args:
        pred: rendered colours, [H, W, 3] or [N, H, W, 3], float, differentiable.
        target: reference colours, same shape.
        mask: optional pixels to score, [H, W] or [N, H, W], bool.
        max_val: peak value (1 for images in [0, 1]).

    Returns:
        Scalar tensor (``inf`` for identical images).
    """
    pred, target = _image_pair(pred, target)
    se = (pred - target) ** 2
    if mask is None:
        mse = se.mean(dim=(1, 2, 3))
    else:
        m = mask if mask.ndim == 3 else mask[None]
        if tuple(m.shape) != tuple(pred.shape[:3]):
            raise ValueError(f"mask must have shape {list(pred.shape[:3])}, got {list(mask.shape)}")
        m = m.to(pred.dtype)[..., None]
        mse = (se * m).sum(dim=(1, 2, 3)) / (3 * m.sum(dim=(1, 2, 3))).clamp_min(1)
    return (10 * torch.log10(max_val ** 2 / mse)).mean()


def ssim(pred: torch.Tensor, target: torch.Tensor, *, window: int = 11, sigma: float = 1.5,
         k1: float = 0.01, k2: float = 0.03, data_range: float = 1.0) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, averaged over pixels,
    channels and images.

    Statistics are population (not sample) moments over the ``valid`` window positions, matching
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)``.

    Args:
        pred: [H, W, 3] or [N, H, W, 3], float, differentiable; H and W >= ``window``.
        target: same shape.
        window: side of the Gaussian window [pixels], odd.
        sigma: standard deviation of the window [pixels].
        k1: luminance stabiliser, times ``data_range``.
        k2: contrast stabiliser, times ``data_range``.
        data_range: value range of the images (1 for [0, 1]).

    References:
        Wang, Bovik, Sheikh, Simoncelli, "Image quality assessment: from error visibility to
        structural similarity", IEEE TIP 2004.
    """
    pred, target = _image_pair(pred, target)
    if pred.shape[1] < window or pred.shape[2] < window:
        raise ValueError(f"images must be at least {window}x{window}, got {pred.shape[2]}x{pred.shape[1]}")
    g = _gaussian_window(window, sigma, pred.dtype, pred.device)
    x, y = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    # one separable blur of all five moments at once (5 x 3 channels, grouped)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    c = stack.shape[1]
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, window)
    wy = g.view(1, 1, -1, 1).expand(c, 1, window, 1)
    blurred = torch.nn.functional.conv2d(torch.nn.functional.conv2d(stack, wx, groups=c), wy, groups=c)
    mx, my, exx, eyy, exy = blurred.chunk(5, dim=1)
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()
