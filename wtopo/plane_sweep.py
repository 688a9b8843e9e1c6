# SPDX-License-Identifier: Apache-2.0
"""The plane sweep's score on CPU and CUDA through Warp (kernels in ``kernels/plane_sweep.py``): for every
hypothesis plane and reference pixel, the mean of the best window NCCs against the source views.

Per chunk of planes, three launches: warp every source into the reference view on each plane (the cameras'
own projection, so distortion and skew need no undistortion; bilinear with zero padding), sum each window's
rows, then each window's columns and score. This replaces a torch formulation of about sixty operations per
chunk over the same tensors (``tests/reference/plane_sweep.py``), whose running-sum box filters dominated the
sweep's time. It is :func:`wtopo.geometry.mvs.plane_sweep_points`' score; nothing here is differentiated.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from . import _bridge
from ._validate import require_tensor
from .kernels import plane_sweep as _k

__all__ = ["LevelPlanes", "SweepReference", "plane_costs"]

_CHUNK_BYTES = 256 * 2**20  # bytes of per-chunk arrays (samples, row sums, validity) held at once on the CPU ...
_CUDA_CHUNK_BYTES = 2**30  # ... and on CUDA, where a chunk's launches must be long enough to hide the host's time
_MIN_CHUNK = 256  # threads per CPU launch at least
_CPU_STRIP = 64  # pixels of a row (or column) per CPU thread, whose window sums slide along it: 6 % faster than 16


class SweepReference(NamedTuple):
    """The reference view, float32 on one device.

    Attributes:
        gray: grey levels ``[H, W]``.
        mean: per pixel, the mean grey level of the window centred there over its in-image pixels ``[H, W]``.
        var: per pixel, that window's variance (population) ``[H, W]``.
        dirs: world ray directions through the pixel centres ``[H, W, 3]`` (camera z = 1, as
            :meth:`wtopo.Camera.pixel_rays`); every ray starts at the camera centre, which the sources' rows
            (:func:`wtopo.multiview_ncc.source_params`) carry.
    """

    gray: torch.Tensor
    mean: torch.Tensor
    var: torch.Tensor
    dirs: torch.Tensor


class LevelPlanes(NamedTuple):
    """Level planes (across the capture's up direction), float32 on the reference's device.

    Attributes:
        heights: the planes' heights along up ``[P]``, world units.
        camera_height: per reference pixel, its ray origin's height ``[H, W]``.
        rate: per reference pixel, the height its ray gains per unit of z-depth ``[H, W]`` (kept off zero).
        lo, hi: a pixel's depth on a plane counts within ``[lo, hi]`` (world units); outside it is -1 (no depth).
    """

    heights: torch.Tensor
    camera_height: torch.Tensor
    rate: torch.Tensor
    lo: float
    hi: float


def _validate(reference, sources, params, planes, half, best) -> None:
    require_tensor("reference.gray", reference.gray, ndim=2, dtypes=(torch.float32,))
    H, W = reference.gray.shape
    dev = reference.gray.device
    for name, t, shape in (("reference.mean", reference.mean, (H, W)), ("reference.var", reference.var, (H, W)),
                           ("reference.dirs", reference.dirs, (H, W, 3))):
        require_tensor(name, t, shape=shape, dtypes=(torch.float32,))
    require_tensor("sources", sources, ndim=3, dtypes=(torch.float32,))
    K = sources.shape[0]
    if not 1 <= K <= _k.MAX_SOURCES:
        raise ValueError(f"sources must hold 1 to {_k.MAX_SOURCES} images, got {K}")
    if tuple(sources.shape[1:]) != (H, W):
        raise ValueError(f"sources must be [K, {H}, {W}] like reference.gray, got {list(sources.shape)}")
    require_tensor("params", params, shape=(K, 23), dtypes=(torch.float32,))
    if isinstance(planes, LevelPlanes):
        require_tensor("planes.heights", planes.heights, ndim=1, dtypes=(torch.float32,))
        for name, t in (("planes.camera_height", planes.camera_height), ("planes.rate", planes.rate)):
            require_tensor(name, t, shape=(H, W), dtypes=(torch.float32,))
        if not planes.lo <= planes.hi:
            raise ValueError(f"planes.lo must be <= planes.hi, got {planes.lo!r} and {planes.hi!r}")
        tensors = (planes.heights, planes.camera_height, planes.rate)
    else:
        require_tensor("planes", planes, ndim=1, dtypes=(torch.float32,))
        tensors = (planes,)
    for name, t in (("reference.mean", reference.mean), ("reference.var", reference.var),
                    ("reference.dirs", reference.dirs), ("sources", sources), ("params", params),
                    *(("planes", t) for t in tensors)):
        if t.device != dev:
            raise ValueError(f"{name} must be on {dev} like reference.gray, got {t.device}")
    if isinstance(half, bool) or not isinstance(half, int) or half < 0:
        raise ValueError(f"half must be an int >= 0, got {half!r}")
    if isinstance(best, bool) or not isinstance(best, int) or not 1 <= best <= K:
        raise ValueError(f"best must be an int in [1, {K}], got {best!r}")


def plane_costs(reference: SweepReference, sources: torch.Tensor, params: torch.Tensor,
                planes: torch.Tensor | LevelPlanes, *, half: int, best: int, min_texture: float) -> torch.Tensor:
    """Per plane and reference pixel, the mean of the ``best`` largest window NCCs against the ``sources``.

    Args:
        reference: the reference view (:class:`SweepReference`).
        sources: the sources' grey images ``[K, H, W]`` float32 (the reference's size), ``1 <= K <= 8``.
        params: the sources' rows ``[K, 23]`` float32 (:func:`wtopo.multiview_ncc.source_params` of the
            reference camera and each source).
        planes: inverse depths ``[P]`` (1 / world units) of planes facing the reference camera, or
            :class:`LevelPlanes`.
        half: the window is ``2 half + 1`` pixels a side, clipped to the image (moments over its in-image pixels).
        best: how many of each window's source NCCs (the largest) are averaged.
        min_texture: a source window whose grey-level variance is at most this scores -1.

    Returns:
        ``[P, H, W]`` float32 in [-1, 1] (up to round-off). A source scores -1 where the window's centre lands
        behind it, outside its image, at a depth that is not positive (a level plane's outside ``[lo, hi]``), or on
        an untextured window; the reference's own texture is not tested here. Not differentiable.

    Raises:
        TypeError: non-tensors or another dtype than float32.
        ValueError: wrong shapes, mismatched devices, ``half`` or ``best`` out of range.
    """
    _validate(reference, sources, params, planes, half, best)
    level = isinstance(planes, LevelPlanes)
    values = planes.heights if level else planes
    H, W = reference.gray.shape
    K = sources.shape[0]
    P = int(values.shape[0])
    dev = reference.gray.device
    cost = torch.empty(P, H, W, dtype=torch.float32, device=dev)
    if P == 0:
        return cost
    per_plane = H * W * (4 * K + 12 * K + 4)  # samples, row sums and validity bits of one plane
    wdev = _bridge.warp_device(dev)
    chunk = max(1, min(P, (_CHUNK_BYTES if wdev.is_cpu else _CUDA_CHUNK_BYTES) // per_plane))
    if level:
        height, rate, lo, hi, family = planes.camera_height, planes.rate, float(planes.lo), float(planes.hi), _k.LEVEL
    else:
        height = rate = reference.mean  # not read
        lo, hi, family = 0.0, 0.0, _k.FRONTO
    args = [_bridge.to_warp(t.contiguous()) for t in (height, rate)]
    dirs = _bridge.to_warp(reference.dirs.contiguous(), _bridge.vec_dtype(reference.dirs))
    images, prm = _bridge.to_warp(sources.contiguous()), _bridge.to_warp(params.contiguous())
    gray, mean, var = (_bridge.to_warp(t.contiguous()) for t in (reference.gray, reference.mean, reference.var))
    warped = torch.empty(chunk, K, H, W, dtype=torch.float32, device=dev)
    rows = torch.empty(chunk, K, H, W, 3, dtype=torch.float32, device=dev)
    valid = torch.empty(chunk, H, W, dtype=torch.int32, device=dev)
    strip = _CPU_STRIP if wdev.is_cpu else 1
    strips, col_strips = -(-W // strip), -(-H // strip)
    with _bridge.torch_stream(wdev, dev):
        for s in range(0, P, chunk):
            n = min(chunk, P - s)
            w_n, r_n, v_n = warped[:n], rows[:n], valid[:n]
            w_a, v_a = _bridge.to_warp(w_n), _bridge.to_warp(v_n)
            r_a = _bridge.to_warp(r_n, _bridge.vec_dtype(r_n))
            _bridge.launch_split(_k.warp_sources_kernel, n * H * strips,
                                 [strip, _bridge.to_warp(values[s:s + n].contiguous()), family, *args, lo, hi, dirs,
                                  images, prm], [w_a, v_a], device=wdev, min_chunk=_MIN_CHUNK)
            _bridge.launch_split(_k.window_rows_kernel, n * K * H * strips, [strip, w_a, gray, int(half)], [r_a],
                                 device=wdev, min_chunk=_MIN_CHUNK)
            _bridge.launch_split(_k.window_costs_kernel, n * col_strips * W,
                                 [strip, r_a, v_a, mean, var, int(half), int(best), float(min_texture)],
                                 [_bridge.to_warp(cost[s:s + n])], device=wdev, min_chunk=_MIN_CHUNK)
    return cost
