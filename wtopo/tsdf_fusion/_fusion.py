# SPDX-License-Identifier: Apache-2.0
"""The validated inputs of one :func:`wtopo.tsdf_fusion.fuse_tsdf` call on its device (views, block flags)
and the slab loop that fuses its grid."""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from .. import _bridge
from .._profile import section
from ..camera import Camera
from ..kernels import tsdf_fusion as _k
from ._slab import _pyramid

BLOCK = 8
"""Nodes per side of a block of the block test: 8 keeps the test's cost (one test per block and view)
below the fusion's while a surface's band covers a few per cent of the blocks of a 384^3 grid."""

SLAB_NODES = 1 << 25
"""Default most nodes fused per slab: ~350 MB of slab arrays (8 bytes per node, marching cubes' 2)."""

_MARGIN_PX = 1.0  # block test: a box's pixel range is grown by a pixel (rounding of the corner projections)
_MIN_THREAD_NODES = 4096  # CPU: nodes per thread below which a launch is not split
_MIN_THREAD_BLOCKS = 64  # CPU: blocks per thread below which the block test is not split


def _point(name: str, value) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be 3 numbers, got {value!r}") from None
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return a


def _positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return v


def _host_map(name: str, value, shape: tuple[int, ...]) -> torch.Tensor:
    """A depth or colour map as a float32 tensor of ``shape`` (wherever it lives), checked finite."""
    if isinstance(value, torch.Tensor):
        t = value.detach()
    else:
        try:
            t = torch.as_tensor(np.asarray(value))
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be an array or tensor, got {type(value).__name__}") from None
    if not (t.is_floating_point() or t.dtype in (torch.uint8, torch.int32, torch.int64)):
        raise TypeError(f"{name} must hold numbers, got dtype {t.dtype}")
    if tuple(t.shape) != shape:
        raise ValueError(f"{name} must have shape {list(shape)} (its camera's image), got {list(t.shape)}")
    t = t.to(torch.float32)
    from .._validate import require_finite

    require_finite(name, t)
    return t


def _view_struct(cam: Camera, far: float, offset: int) -> _k.View:
    from ..geometry.depth_warp import pinhole_warp

    v = _k.View()
    R = cam.R.astype(np.float32)
    v.rotation = wp.mat33(*R.ravel().tolist())
    v.translation = wp.vec3(*cam.t.astype(np.float32).tolist())
    v.fx, v.fy = float(cam.K[0, 0]), float(cam.K[1, 1])
    v.cx, v.cy, v.skew = float(cam.K[0, 2]), float(cam.K[1, 2]), float(cam.K[0, 1])
    d = np.zeros(5) if cam.distortion is None else cam.distortion
    v.k1, v.k2, v.p1, v.p2, v.k3 = (float(x) for x in d)
    v.distorted = int(cam.distortion is not None)
    # the lens's field (depth_warp measures it once per intrinsics): beyond it the polynomial folds back
    v.radius2 = float(pinhole_warp(cam).field_radius ** 2) if cam.distortion is not None else 0.0
    v.width, v.height = cam.width, cam.height
    v.far = float(min(far, 3.0e38))
    v.offset = int(offset)
    return v


def _grid_shape(lower: np.ndarray, upper: np.ndarray, voxel: float) -> tuple[int, int, int]:
    # nodes lower + i * voxel up to the first at or past upper (1e-9: upper on a node is not one more)
    n = np.ceil((upper - lower) / voxel - 1e-9).astype(np.int64) + 1
    return tuple(int(max(2, x)) for x in n)

class _Fusion:
    """Validated inputs of one fusion on its device: views, block flags; :meth:`slabs` fuses the grid."""

    def __init__(self, cameras, depths, colors, lower, upper, voxel, truncation, far, device, cull):
        cameras, depths = list(cameras), list(depths)
        n = len(cameras)
        for i, c in enumerate(cameras):
            if not isinstance(c, Camera):
                raise TypeError(f"cameras[{i}] must be a wtopo.Camera, got {type(c).__name__}")
        if len(depths) != n:
            raise ValueError(f"depths must hold one map per camera ({n}), got {len(depths)}")
        if colors is not None:
            colors = list(colors)
            if len(colors) != n:
                raise ValueError(f"colors must hold one image per camera ({n}), got {len(colors)}")
        lo, hi = _point("lower", lower), _point("upper", upper)
        if np.any(hi <= lo):
            raise ValueError(f"upper must exceed lower on every axis, got lower={lo.tolist()}, upper={hi.tolist()}")
        self.voxel = _positive("voxel", voxel)
        self.truncation = _positive("truncation", truncation)
        if far is None:
            far = [math.inf] * n
        else:
            far = list(far)
            if len(far) != n:
                raise ValueError(f"far must hold one cut-off per camera ({n}), got {len(far)}")
            for i, f in enumerate(far):
                if isinstance(f, bool) or not isinstance(f, (int, float, np.floating, np.integer)) or not float(f) > 0:
                    raise ValueError(f"far[{i}] must be a number > 0, got {f!r}")
        if device is None:
            device = next((d.device for d in depths if isinstance(d, torch.Tensor)), torch.device("cpu"))
        self.device = torch.device(device)
        self.lower = lo
        self.shape = _grid_shape(lo, hi, self.voxel)
        sizes = [(c.height, c.width) for c in cameras]
        if sum(h * w for h, w in sizes) >= 2**31:
            raise ValueError(f"the views must hold fewer than 2^31 pixels in all (int32 offsets), got "
                             f"{sum(h * w for h, w in sizes)}")
        # every map is checked (size, finite) before anything is launched
        dmaps = [_host_map(f"depths[{i}]", d, sizes[i]) for i, d in enumerate(depths)]
        cmaps = None if colors is None else [_host_map(f"colors[{i}]", c, sizes[i] + (3,))
                                             for i, c in enumerate(colors)]
        self.n_views = n
        self.has_color = cmaps is not None
        self.cull = bool(cull)
        self.wdev = _bridge.warp_device(self.device)
        if n == 0:
            return
        with self.scope(), section("tsdf_upload"):
            offsets = np.cumsum([0] + [h * w for h, w in sizes])
            self.depth = wp.from_torch(torch.cat([d.reshape(-1) for d in dmaps]).to(self.device).contiguous())
            if cmaps is not None:
                rgb = torch.cat([c.reshape(-1, 3) for c in cmaps]).to(self.device)
                self.color = wp.from_torch((rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).contiguous(),
                                           dtype=_k.vec3ub)
            else:
                self.color = wp.empty(1, dtype=_k.vec3ub, device=self.wdev)
            self.views = wp.array([_view_struct(c, float(f), int(o)) for c, f, o in zip(cameras, far, offsets)],
                                  dtype=_k.View, device=self.wdev)
        self.sizes = sizes

    def scope(self):
        """Warp on the fusion's device and, on CUDA, torch's current stream (ordered with the torch ops)."""
        return _bridge._on_torch_stream(self.wdev, self.device)  # noqa: SLF001 - the bridge's one stream scope

    def _volume(self) -> _k.Volume:
        vol = _k.Volume()
        vol.lower = wp.vec3(*self.lower.astype(np.float32).tolist())
        vol.voxel, vol.truncation = self.voxel, self.truncation
        vol.nx, vol.ny, vol.block = self.shape[0], self.shape[1], BLOCK
        vol.nbx, vol.nby, vol.nbz = (-(-s // BLOCK) for s in self.shape)
        vol.k0, vol.nz = 0, self.shape[2]
        return vol

    def _blocks(self, vol: _k.Volume) -> wp.array:
        if not self.cull:
            return wp.empty((1, 1, 1), dtype=wp.uint8, device=self.wdev)
        with section("tsdf_blocks"):
            levels, dmin, dmax = _pyramid(self.views, self.depth, self.sizes, self.wdev)
            blocks = wp.empty((vol.nbx, vol.nby, vol.nbz), dtype=wp.uint8, device=self.wdev)
            _bridge.launch_split(_k.mark_blocks_kernel, vol.nbx * vol.nby * vol.nbz,
                                 [vol, self.views, levels, dmin, dmax, _MARGIN_PX], [blocks], device=self.wdev,
                                 min_chunk=_MIN_THREAD_BLOCKS)
        return blocks

    def slabs(self, slab_nodes: int):
        """Yield ``(k0, tsdf, observed, colors or None)`` per z-slab (Warp arrays ``[X, Y, layers]``, node
        layers ``k0 ..``); consecutive slabs share one node layer. Run inside :meth:`scope`."""
        nx, ny, nz = self.shape
        vol = self._volume()
        blocks = self._blocks(vol)
        per_slab = max(2, slab_nodes // (nx * ny))
        k0 = 0
        while k0 < nz - 1:
            k1 = min(nz, k0 + per_slab)
            vol.k0, vol.nz = k0, k1 - k0
            tsdf = wp.empty((nx, ny, k1 - k0), dtype=wp.float32, device=self.wdev)
            observed = wp.empty((nx, ny, k1 - k0), dtype=wp.uint8, device=self.wdev)
            color = wp.empty((nx, ny, k1 - k0) if self.has_color else (1, 1, 1), dtype=_k.vec3ub, device=self.wdev)
            with section("tsdf_integrate"):
                _bridge.launch_split(_k.integrate_kernel, nx * ny * (k1 - k0),
                                     [vol, self.views, self.depth, self.color, int(self.has_color), blocks,
                                      int(self.cull)],
                                     [tsdf, observed, color], device=self.wdev, min_chunk=_MIN_THREAD_NODES)
            yield k0, tsdf, observed, (color if self.has_color else None)
            k0 = k1 - 1


def _slab_limit(slab_nodes, shape) -> int:
    layer = shape[0] * shape[1]
    slab_nodes = SLAB_NODES if slab_nodes is None else slab_nodes
    if isinstance(slab_nodes, bool) or not isinstance(slab_nodes, int) or slab_nodes < 2 * layer:
        raise ValueError(f"slab_nodes must be an int >= two node layers ({2 * layer}), got {slab_nodes!r}")
    return slab_nodes
