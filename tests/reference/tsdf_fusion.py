# SPDX-License-Identifier: Apache-2.0
"""NumPy reference of TSDF fusion: every grid node projected into every view, float64, no block test.

The same rule as :mod:`wtopo.kernels.tsdf_fusion` written out over arrays: node ``(i, j, k)`` at
``lower + (i, j, k) * voxel``; per view the node goes through the camera's pose, ``x / z``, OpenCV
distortion (nothing beyond the lens's field radius), the skewed ``K``; it reads the depth of the
pixel it falls in; ``sdf = (d - z) * |p| / z`` contributes ``min(1, sdf / truncation)`` with weight 1
when ``0 < d < far`` and ``sdf > -truncation``; the mean is moved off 0 by ``MIN_ABS_TSDF``. A node no
view contributes to is *seen free* when some view sees it on a pixel without depth (``d <= 0`` or
``d >= far``), else *hidden* when some view's valid depth lies more than the truncation before it.
"""

from __future__ import annotations

import numpy as np

from wtopo.geometry.depth_warp import pinhole_warp
from wtopo.kernels.tsdf_fusion import MIN_ABS_TSDF

__all__ = ["tsdf_reference"]


def tsdf_reference(cameras, depths, colors, *, lower, upper, voxel: float, truncation: float, far=None):
    """Dense TSDF of ``depths`` (and mean ``colors``) on the grid of :func:`wtopo.tsdf_fusion.tsdf_volume`.

    Args:
        cameras: :class:`wtopo.Camera` per view.
        depths: z-depth [H, W] per view (0 = none).
        colors: RGB [H, W, 3] in [0, 1] per view, or ``None``.
        lower: node ``(0, 0, 0)`` [3].
        upper: the grid reaches at least this corner [3].
        voxel: node spacing.
        truncation: truncation distance.
        far: per-view depth cut-off or ``None``.

    Returns:
        ``(tsdf [X, Y, Z] float64 (1 where unobserved), observed [X, Y, Z] bool, free [X, Y, Z] bool,
        hidden [X, Y, Z] bool, colour [X, Y, Z, 3] float64 in 8-bit units or None)``.
    """
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    shape = tuple(int(max(2, n)) for n in np.ceil((upper - lower) / voxel - 1e-9).astype(np.int64) + 1)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    pts = lower + idx * voxel
    total = np.zeros(len(pts))
    weight = np.zeros(len(pts))
    rgb = np.zeros((len(pts), 3))
    free = np.zeros(len(pts), bool)
    behind = np.zeros(len(pts), bool)
    far = [np.inf] * len(cameras) if far is None else far
    for i, cam in enumerate(cameras):
        pc = pts @ cam.R.T + cam.t
        z = pc[:, 2]
        front = z > 1e-12
        zs = np.where(front, z, 1.0)
        xy = pc[:, :2] / zs[:, None]
        if cam.distortion is not None:
            front &= (xy ** 2).sum(1) <= pinhole_warp(cam).field_radius ** 2
        xy = cam.distort(xy)
        u = cam.K[0, 0] * xy[:, 0] + cam.K[0, 1] * xy[:, 1] + cam.K[0, 2]
        v = cam.K[1, 1] * xy[:, 1] + cam.K[1, 2]
        seen = front & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        col = np.where(seen, np.floor(u), 0).astype(np.int64)
        row = np.where(seen, np.floor(v), 0).astype(np.int64)
        d = np.asarray(depths[i], np.float64)[row, col]
        sdf = (d - z) * np.linalg.norm(pc, axis=1) / zs
        ok = seen & (d > 0) & (d < far[i]) & (sdf > -truncation)
        total += np.where(ok, np.minimum(1.0, sdf / truncation), 0.0)
        weight += ok
        free |= seen & ~((d > 0) & (d < far[i]))
        behind |= seen & (d > 0) & (d < far[i]) & (sdf <= -truncation)
        if colors is not None:
            c = np.round(np.clip(np.asarray(colors[i], np.float64), 0, 1) * 255)[row, col]
            rgb += np.where(ok[:, None], c, 0.0)
    observed = weight > 0
    tsdf = np.where(observed, total / np.maximum(weight, 1), 1.0)
    small = observed & (np.abs(tsdf) < MIN_ABS_TSDF)
    tsdf[small] = np.where(tsdf[small] < 0, -MIN_ABS_TSDF, MIN_ABS_TSDF)
    color = None if colors is None else (rgb / np.maximum(weight, 1)[:, None]).reshape(shape + (3,))
    free &= ~observed
    hidden = behind & ~free & ~observed
    return tsdf.reshape(shape), observed.reshape(shape), free.reshape(shape), hidden.reshape(shape), color
