# SPDX-License-Identifier: Apache-2.0
"""Per-view inputs of the rasterizer: pixel rays and tile tables (cached on the camera), the
kernels' camera record, and the default near / far planes (host median or on the device)."""

from __future__ import annotations

import ctypes
import math

import numpy as np
import torch
import warp as wp

from .. import _bridge
from ..camera import Camera
from ..kernels import rasterize as _k
from ._config import RasterConfig


def _camera_tables(camera: Camera, device, dtype, tile_size: int):
    """Rays [H, W, 3] and the normalised-coordinate range tables (cached on the camera).

    The tables are ``(colx_min, colx_max, rowy_min, rowy_max)`` per tile column / row, then the same
    four per pixel column / row (the CPU tile kernels' pixel rectangles, ``kernels/rasterize_tiles.py``),
    float64 views of one packed tensor (:func:`_packed_tables`).
    """
    dirs, tables, _ = _camera_cached(camera, device, dtype, tile_size)
    return dirs, tables


def _camera_cached(camera: Camera, device, dtype, tile_size: int):
    return camera.cached(("wtopo.rasterize.tables", str(device), dtype, tile_size),
                         lambda: _build_camera_tables(camera, device, dtype, tile_size))


def _packed_tables(camera: Camera, device, dtype, tile_size: int) -> torch.Tensor:
    """The eight tables of :func:`_camera_tables` end to end in one float64 tensor on ``device`` (cached)."""
    return _camera_cached(camera, device, dtype, tile_size)[2]


def _table_views(packed: torch.Tensor, width: int, height: int, tile_size: int) -> tuple:
    """The eight Warp views of a :func:`_packed_tables` tensor of a ``width x height`` view."""
    tx, ty = -(-width // tile_size), -(-height // tile_size)
    out, o = [], 0
    for k in (tx, tx, ty, ty, width, width, height, height):
        out.append(_bridge.to_warp(packed[o:o + k]))
        o += k
    return tuple(out)


def _range_tables(x: np.ndarray, y: np.ndarray, size: int) -> tuple[np.ndarray, ...]:
    """Min / max of ``x`` per column group and of ``y`` per row group of ``size`` pixels."""
    h, w = x.shape
    tx, ty = -(-w // size), -(-h // size)
    colx_min = np.array([x[:, j * size:(j + 1) * size].min() for j in range(tx)])
    colx_max = np.array([x[:, j * size:(j + 1) * size].max() for j in range(tx)])
    rowy_min = np.array([y[i * size:(i + 1) * size].min() for i in range(ty)])
    rowy_max = np.array([y[i * size:(i + 1) * size].max() for i in range(ty)])
    # binary searches need non-decreasing tables; a lens that folds the image gets full ranges
    if np.any(np.diff(colx_min) < 0) or np.any(np.diff(colx_max) < 0):
        colx_min[:], colx_max[:] = -np.inf, np.inf
    if np.any(np.diff(rowy_min) < 0) or np.any(np.diff(rowy_max) < 0):
        rowy_min[:], rowy_max[:] = -np.inf, np.inf
    return colx_min, colx_max, rowy_min, rowy_max


def _build_camera_tables(camera: Camera, device, dtype, tile_size: int):
    """What :func:`_camera_cached` caches: the rays, the tables' views and their packed tensor."""
    _, dirs = camera.pixel_rays(device, dtype)
    d_cam = dirs.detach().cpu().double().numpy() @ camera.R.T
    x = d_cam[..., 0]
    y = d_cam[..., 1]
    packed = torch.as_tensor(np.concatenate([*_range_tables(x, y, tile_size), *_range_tables(x, y, 1)]),
                             dtype=torch.float64).to(device)
    return dirs, _table_views(packed, camera.width, camera.height, tile_size), packed


def _depth_row4(camera: Camera, device, dtype) -> torch.Tensor:
    """Third row of the world-to-camera rotation and the translation's z [4] (op dtype, on the device, cached on the
    camera: no copy per call): a centre's z-depth is ``means @ row[:3] + row[3]``."""
    return camera.cached(("wtopo.rasterize.depth_row4", str(device), dtype),
                         lambda: torch.as_tensor([*camera.R[2], camera.t[2]], dtype=dtype, device=device))


def _record_type(dtype):
    """The :class:`wtopo.kernels.rasterize.CameraRecord` struct of the op dtype."""
    return _k.CAMERA[wp.float64 if dtype == torch.float64 else wp.float32]


def _record_base(camera: Camera, device, dtype, filter_sigma: float) -> torch.Tensor:
    """The view's camera record as bytes on ``device`` (uint8 tensor, its clip planes zero): made once per camera,
    device, dtype and filter (cached on the camera: one host-to-device copy per view)."""

    def build():
        rec = _record_type(dtype)()
        fx, skew, cx = (float(v) for v in camera.K[0])
        dist = camera.distortion if camera.distortion is not None else np.zeros(5)
        rec.R = type(rec.R)(*(float(v) for v in camera.R.reshape(-1)))
        rec.t = type(rec.t)(*(float(v) for v in camera.t))
        rec.center = type(rec.center)(*(float(v) for v in camera.center))
        rec.fx, rec.fy, rec.cx, rec.cy, rec.skew = fx, float(camera.K[1, 1]), cx, float(camera.K[1, 2]), skew
        rec.k1, rec.k2, rec.p1, rec.p2, rec.k3 = (float(v) for v in dist)
        rec.filter_inv_sq = 1.0 / float(filter_sigma) ** 2
        rec.width, rec.height = int(camera.width), int(camera.height)
        c = rec.__ctype__()
        return torch.frombuffer(bytearray(ctypes.string_at(ctypes.addressof(c), ctypes.sizeof(c))),
                                dtype=torch.uint8).to(device)

    return camera.cached(("wtopo.rasterize.record", str(device), dtype, float(filter_sigma)), build)


def _camera_record(camera: Camera, clip: torch.Tensor, dtype, filter_sigma: float) -> wp.array:
    """Everything the kernels read per view: a one-element array of
    :class:`wtopo.kernels.rasterize.CameraRecord` of the op dtype in ``clip``'s device memory (the kernels'
    ``cams``), its own copy per call (an op's backward reads the record of its own forward).

    Values are computed in float64 on the host and rounded once to the op dtype (once per view); ``clip``
    ([near, far] float64 [2] on the device) is written into the copy on the device, no host synchronisation.
    """
    return _record_from_base(_record_base(camera, clip.device, dtype, filter_sigma), clip, dtype)


def _record_from_base(base: torch.Tensor, clip: torch.Tensor, dtype) -> wp.array:
    """A copy of a :func:`_record_base` with ``clip`` written into its ``near`` and ``far`` fields (adjacent), as
    the kernels' ``cams``."""
    rec_type = _record_type(dtype)
    blob = base.clone()
    off = rec_type.ctype.near.offset
    blob[off:off + 2 * dtype.itemsize].view(dtype).copy_(clip)
    return _bridge.struct_view(blob, rec_type)


def _centre_depths(means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """z-depths of the surfel centres [N] (op dtype, on their device).

    On the CPU with NumPy, one thread, term by term: torch's matrix-vector product and masked selection
    hand a [12k] problem to their thread pool, which on a busy 2-core machine waits for a time slice
    (measured 8 ms each at load 2-4, against 0.1 ms on one thread).
    """
    if means.device.type == "cpu":
        m = means.detach().numpy()
        r = camera.R[2].astype(m.dtype)
        z = m[:, 0] * r[0]
        z += m[:, 1] * r[1]
        z += m[:, 2] * r[2]
        z += m.dtype.type(camera.t[2])
        return torch.from_numpy(z)
    row = _depth_row4(camera, means.device, means.dtype)
    return means.detach() @ row[:3] + row[3]


def _default_clip(means: torch.Tensor, camera: Camera, near, far, config: RasterConfig):
    if near is not None and far is not None:
        return float(near), float(far)
    z = _centre_depths(means, camera)
    if z.device.type == "cpu":  # NumPy: one thread (see _centre_depths); the lower middle, as torch.median
        z = z.numpy()
        z = z[z > 0]
        zref = float(np.partition(z, (z.size - 1) // 2)[(z.size - 1) // 2]) if z.size else 1.0
    else:
        z = z[z > 0]
        zref = float(z.median()) if z.numel() else 1.0  # host sync: scene-relative clip defaults
    near = config.near_fraction * zref if near is None else float(near)
    far = config.far_multiple * zref if far is None else float(far)
    if not near < far:
        raise ValueError(f"near must be < far, got near={near}, far={far} (one was defaulted from the scene)")
    return near, far


def _clip_from_host(near: float, far: float, device) -> torch.Tensor:
    """``[near, far]`` float64 [2] on ``device`` from host values (two fills: no blocking copy)."""
    clip = torch.empty(2, dtype=torch.float64, device=device)
    clip[0] = near
    clip[1] = far
    return clip


def _default_clip_device(means: torch.Tensor, camera: Camera, config: RasterConfig) -> torch.Tensor:
    """:func:`_default_clip` with both planes defaulted, computed on the device without a host sync.

    Same values: ``torch.median`` is the lower middle of the sorted positive depths, picked here by
    index from a sort that sends the others to ``+inf``; the products are taken in float64 as the
    host path does.
    """
    if means.shape[0] == 0:
        return _clip_from_host(config.near_fraction, config.far_multiple, means.device)
    return _clip_from_row(means, _depth_row4(camera, means.device, means.dtype), config)


def _clip_from_row(means: torch.Tensor, row4: torch.Tensor, config: RasterConfig) -> torch.Tensor:
    """:func:`_default_clip_device` of N > 0 surfels with the camera as data (:func:`_depth_row4`)."""
    z = means.detach() @ row4[:3] + row4[3]
    pos = z > 0
    k = pos.sum()
    zs = torch.where(pos, z, torch.full_like(z, math.inf)).sort().values
    zref = torch.where(k > 0, zs.gather(0, ((k - 1).clamp_min(0) // 2).view(1)), torch.ones_like(zs[:1])).double()
    return torch.cat([zref * config.near_fraction, zref * config.far_multiple])
