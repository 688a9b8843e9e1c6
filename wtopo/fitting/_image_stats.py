# SPDX-License-Identifier: Apache-2.0
"""What the plan measures in the training images (:mod:`wtopo.fitting.plan`): colour spread, the texture a
patch comparison can match, and how much colours change between views."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..geometry.mvs import gray as _gray

__all__ = ["as_np", "texture_std", "window_std", "view_inconsistency"]

# a window whose grey levels all lie above _CLIPPED[1] or all below _CLIPPED[0] is clipped (saturated white,
# black): no texture to measure there, and it is left out of the median (DTU scan24, whose white table and black
# backdrop clip: 0.018 over every window, 0.035 without the clipped ones; the bunny 0.1054 -> 0.1056)
_CLIPPED = (0.05, 0.98)


def as_np(x):
    """``x`` (tensor, array or None) as a numpy array (None stays None)."""
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def texture_std(images: np.ndarray, masks: np.ndarray | None) -> float:
    """Mean per-channel colour std over the foreground pixels of up to 8 views (images [N, H, W, 3] in [0, 1])."""
    step = max(1, images.shape[0] // 8)
    imgs = images[::step].astype(np.float32)
    if masks is not None:
        m = masks[::step].astype(bool)
        px = imgs[m]
    else:
        px = imgs.reshape(-1, 3)
    if px.shape[0] < 2:
        return 0.0
    return float(px.std(axis=0).mean())


def window_std(images: np.ndarray, masks: np.ndarray | None, window: int = 7) -> float:
    """Median grey-level standard deviation of ``window`` x ``window`` windows over the foreground
    (mask) pixels of up to 8 views: the texture a patch comparison between views can match. Clipped windows
    (every grey level below ``_CLIPPED[0]`` or above ``_CLIPPED[1]``: saturated highlights, black) are left
    out; 0.0 when nothing is left."""
    step = max(1, images.shape[0] // 8)
    g = _gray(torch.as_tensor(images[::step].astype(np.float32)))[:, None]
    pad = window // 2
    mu = F.avg_pool2d(g, window, 1, pad, count_include_pad=False)
    mu2 = F.avg_pool2d(g * g, window, 1, pad, count_include_pad=False)
    std = (mu2 - mu * mu).clamp_min(0).sqrt()[:, 0]
    hi = F.max_pool2d(g, window, 1, pad)[:, 0]
    lo = -F.max_pool2d(-g, window, 1, pad)[:, 0]
    keep = (hi >= _CLIPPED[0]) & (lo <= _CLIPPED[1])
    if masks is not None:
        keep &= torch.as_tensor(masks[::step].astype(bool))
    std = std[keep]
    return float(std.median()) if std.numel() else 0.0


def view_inconsistency(scene, images: np.ndarray, depths: np.ndarray, rng: np.random.Generator) -> float:
    """Mean colour difference of pixels reprojected between neighbouring views via the depth maps."""
    cams = scene.cameras
    n = len(cams)
    centers = np.stack([c.center for c in cams])
    diffs = []
    for a in rng.choice(n, size=min(n, 6), replace=False):
        d = np.linalg.norm(centers - centers[a], axis=1)
        d[a] = np.inf
        b = int(np.argmin(d))
        dep = depths[a]
        ii, jj = np.nonzero(dep > 0)
        if ii.size == 0:
            continue
        pick = rng.choice(ii.size, size=min(ii.size, 2000), replace=False)
        ii, jj = ii[pick], jj[pick]
        dirs = cams[a].pixel_directions_camera()[ii, jj]
        pc = dirs * dep[ii, jj][:, None]
        pw = (pc - cams[a].t) @ cams[a].R  # camera -> world
        uv, z = cams[b].project(pw)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cams[b].width) & (v < cams[b].height)
        if not ok.any():
            continue
        # visible in b: the reprojected depth matches b's depth map
        zb = depths[b][v[ok], u[ok]]
        vis = np.abs(zb - z[ok]) < 0.01 * np.abs(z[ok]).mean()
        if vis.sum() < 10:
            continue
        ca = images[a][ii[ok][vis], jj[ok][vis]]
        cb = images[b][v[ok][vis], u[ok][vis]]
        diffs.append(np.abs(ca - cb).mean())
    return float(np.mean(diffs)) if diffs else float("nan")
