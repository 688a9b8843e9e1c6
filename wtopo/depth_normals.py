# SPDX-License-Identifier: Apache-2.0
"""Normals of a rendered depth map (2DGS's "surface normal" from depth), one Warp launch."""

from __future__ import annotations

import torch

from . import _bridge
from ._validate import require_finite, require_positive, require_same_device, require_tensor
from .kernels import depth_normals as _k

__all__ = ["depth_normals"]

_CPU_RUN = 64  # pixels per kernel thread on the CPU (a Warp CPU thread costs about as much as a pixel)
_MIN_CHUNK = 64  # runs per CPU launch thread at least: a 64 x 64 map is one launch (a split costs tens of us)


def depth_normals(depth: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, valid: torch.Tensor, *,
                  eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals of the surface a z-depth map describes, by central differences, facing the camera.

    For each pixel ``(y, x)`` with ``p = origins + directions * depth``: ``n = cross(p[y, x+1] - p[y, x-1],
    p[y+1, x] - p[y-1, x]) / |.|``, negated where it points along the pixel's ray. Border pixels, pixels
    where the pixel or one of its four neighbours is not ``valid``, and pixels whose cross product is not
    longer than ``eps`` get a zero normal and ``False`` in the mask (2DGS pads its borders with zero).

    Args:
        depth: z-depths [H, W], float32 or float64, world units (the renderer's ``median_depth``).
        origins: ray origins [H, W, 3], same dtype (:meth:`wtopo.Camera.pixel_rays`).
        directions: ray directions [H, W, 3] whose camera-z component is 1, same dtype.
        valid: bool [H, W], the pixels whose depth counts (e.g. covered by the surfels).
        eps: length of the cross product [world units^2] at or below which a pixel has no normal.

    Returns:
        ``(normals [H, W, 3] of depth's dtype, mask bool [H, W])`` on depth's device. Not differentiable:
        both are detached (the fit holds the depth normal fixed as its target).

    Raises:
        TypeError, ValueError: wrong types, dtypes, shapes or devices; non-finite ``depth``, ``origins`` or
            ``directions``; a negative ``eps``.
    """
    require_tensor("depth", depth, ndim=2)
    h, w = depth.shape
    require_tensor("origins", origins, shape=(h, w, 3), dtypes=(depth.dtype,))
    require_tensor("directions", directions, shape=(h, w, 3), dtypes=(depth.dtype,))
    require_tensor("valid", valid, shape=(h, w), dtypes=(torch.bool,))
    device = require_same_device(depth=depth, origins=origins, directions=directions, valid=valid)
    require_positive("eps", eps, allow_zero=True)
    for name, t in (("depth", depth), ("origins", origins), ("directions", directions)):
        require_finite(name, t.detach())
    normals = torch.empty(h, w, 3, dtype=depth.dtype, device=device)
    mask = torch.empty(h, w, dtype=torch.bool, device=device)
    if h == 0 or w == 0:
        return normals, mask
    s = _bridge.float_dtype(depth)
    v3 = _bridge.vec_dtype(origins)
    wdev = _bridge.warp_device(device)
    with _bridge.torch_stream(wdev, device):
        per = 1 if wdev.is_cuda else _CPU_RUN
        _bridge.launch_split(_k.OVERLOADS[s], -(-h * w // per),
                             [_bridge.to_warp(depth), _bridge.to_warp(origins, v3), _bridge.to_warp(directions, v3),
                              _bridge.to_warp(valid.view(torch.uint8)), s(eps), per],
                             [_bridge.to_warp(normals, v3), _bridge.to_warp(mask.view(torch.uint8))], device=wdev,
                             min_chunk=_MIN_CHUNK)
    return normals, mask
