# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference of the fused photometric loss: L1 plus D-SSIM with a full 2-D Gaussian window.

Independent of the separable formulation of ``kernels/photometric.py``: the window is the outer
product of the 1-D Gaussian, applied as one non-separable convolution per moment; torch autograd
gives the gradient.
"""

from __future__ import annotations

import torch

__all__ = ["photometric_reference"]


def photometric_reference(pred: torch.Tensor, target: torch.Tensor, *, dssim: float = 0.2, window: int = 11,
                          sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03,
                          data_range: float = 1.0) -> torch.Tensor:
    """``(1 - dssim) mean|pred - target| + dssim (1 - mean SSIM)`` of images [H, W, C] (valid window positions)."""
    x = torch.arange(window, dtype=pred.dtype, device=pred.device) - (window - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    w2 = (g[:, None] * g[None, :])[None, None]  # [1, 1, win, win]

    def blur(img):  # [H, W, C] -> [Hv, Wv, C]
        c = img.shape[-1]
        out = torch.nn.functional.conv2d(img.permute(2, 0, 1)[:, None], w2)
        return out[:, 0].permute(1, 2, 0).reshape(img.shape[0] - window + 1, img.shape[1] - window + 1, c)

    y = target
    mx, my = blur(pred), blur(y)
    sxx = blur(pred * pred) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(pred * y) - mx * my
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return (1.0 - dssim) * (pred - y).abs().mean() + dssim * (1.0 - s.mean())
