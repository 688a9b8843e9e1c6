# SPDX-License-Identifier: Apache-2.0
"""TSDF fusion of z-depth (and colour) maps into a mesh with Warp, on CPU or CUDA.

:func:`fuse_tsdf` integrates every view into a dense grid of TSDF nodes, one z-slab at a time, and
extracts each slab's zero level with :func:`wtopo.marching_cubes.marching_cubes`
(:mod:`wtopo.kernels.tsdf_fusion` has the per-node rule). Per slab:

* a block test (blocks of ``BLOCK`` nodes per side, whole grid, once) marks the blocks some view's
  truncation band may reach; nodes of the other blocks are written unobserved without projecting
  (``cull=False`` projects every node: the mesh is the same);
* one launch fuses every view into every node of the slab (one thread per node, all views in its
  loop: nothing is allocated per view);
* marching cubes of the slab in node-index coordinates; a face is kept when both ends of every
  vertex's grid edge were observed, so unobserved nodes make no face and the surface is open where
  nothing was seen; vertex colours are interpolated along the same edges;
* the slab's vertices on the layer it shares with the previous slab are welded to that slab's.

Memory: the views (4 bytes of depth and 3 of colour per pixel, and the block test's depth-range
pyramid of 8 bytes per texel, about 11 per pixel over its levels: some 18 bytes per pixel in all,
0.4 GB for 48 views of 800 x 600), the block flags (1 byte per ``BLOCK^3`` nodes), and per slab at most
``slab_nodes`` nodes of 8 bytes (TSDF, observed flag, colour) plus marching cubes' 2 bytes per
node and its output. With the default ``SLAB_NODES`` (2^25) a slab takes about 350 MB whatever the
grid size: a 768^3 grid is fused in 14 slabs. Only the mesh grows with the grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from . import _bridge
from ._profile import section
from .camera import Camera
from .kernels import tsdf_fusion as _k

__all__ = ["TSDFMesh", "TSDFVolume", "fuse_tsdf", "tsdf_volume", "BLOCK", "SLAB_NODES"]

BLOCK = 8
"""Nodes per side of a block of the block test: 8 keeps the test's cost (one test per block and view)
below the fusion's while a surface's band covers a few per cent of the blocks of a 384^3 grid."""

SLAB_NODES = 1 << 25
"""Default most nodes fused per slab: ~350 MB of slab arrays (8 bytes per node, marching cubes' 2)."""

_MARGIN_PX = 1.0  # block test: a box's pixel range is grown by a pixel (rounding of the corner projections)
_MIN_THREAD_NODES = 4096  # CPU: nodes per thread below which a launch is not split
_MIN_THREAD_BLOCKS = 64  # CPU: blocks per thread below which the block test is not split


@dataclass
class TSDFMesh:
    """What :func:`fuse_tsdf` returns.

    Attributes:
        verts: vertex positions [V, 3], float32, world units (the cameras' frame), on the fusion's device.
        faces: [F, 3] int32 indices into ``verts``, wound so normals point towards the cameras (out
            of the surface: increasing TSDF).
        colors: vertex colours [V, 3] uint8, or ``None`` when no colours were fused.
        shape: nodes of the grid along x, y, z.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    colors: torch.Tensor | None
    shape: tuple[int, int, int]


@dataclass
class TSDFVolume:
    """What :func:`tsdf_volume` returns: the fused grid, node ``(i, j, k)`` at ``lower + (i, j, k) * voxel``.

    Attributes:
        tsdf: mean truncated signed distance in truncation units [X, Y, Z], float32, in ``[-1, 1]``
            (positive in front of the surface); 1 where unobserved.
        observed: [X, Y, Z] bool, whether any view contributed to the node.
        free: [X, Y, Z] bool, unobserved nodes some view's ray crossed on its way to no surface (the
            node projects onto a pixel without depth); ``False`` where observed.
        hidden: [X, Y, Z] bool, unobserved nodes not ``free`` that lie deeper than the truncation
            behind some view's depth.
        colors: mean colour [X, Y, Z, 3] uint8 (0 where unobserved), or ``None``.
        lower: position of node ``(0, 0, 0)`` [3], float64, world units.
        voxel: node spacing, world units.
    """

    tsdf: torch.Tensor
    observed: torch.Tensor
    free: torch.Tensor
    hidden: torch.Tensor
    colors: torch.Tensor | None
    lower: np.ndarray
    voxel: float


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
    from ._validate import require_finite

    require_finite(name, t)
    return t


def _view_struct(cam: Camera, far: float, offset: int) -> _k.View:
    from .fitting.depth_warp import pinhole_warp

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


def _pyramid(views: wp.array, depth: wp.array, sizes: list[tuple[int, int]], device):
    """Depth-range pyramid of every view: ``(levels [L] vec4i (offset, height, width, 0), dmin, dmax)``."""
    h, w = max(s[0] for s in sizes), max(s[1] for s in sizes)
    dims = [(h, w)]
    while dims[-1] != (1, 1):
        dims.append(((dims[-1][0] + 1) // 2, (dims[-1][1] + 1) // 2))
    n = len(sizes)
    offsets = np.cumsum([0] + [n * a * b for a, b in dims])
    dmin = wp.empty(int(offsets[-1]), dtype=wp.float32, device=device)
    dmax = wp.empty(int(offsets[-1]), dtype=wp.float32, device=device)
    wp.launch(_k.depth_range_base_kernel, dim=(n, h, w), inputs=[views, depth, h, w], outputs=[dmin, dmax],
              device=device)
    for li in range(1, len(dims)):
        (sh, sw), (dh, dw) = dims[li - 1], dims[li]
        wp.launch(_k.depth_range_reduce_kernel, dim=(n, dh, dw),
                  inputs=[int(offsets[li - 1]), sh, sw, int(offsets[li]), dh, dw], outputs=[dmin, dmax], device=device)
    levels = wp.array([wp.vec4i(int(o), a, b, 0) for o, (a, b) in zip(offsets[:-1], dims)], dtype=wp.vec4i,
                      device=device)
    return levels, dmin, dmax


class _Seam:
    """Vertices of the last slab's top layer, to weld the next slab's bottom layer onto."""

    def __init__(self):
        self.xy: torch.Tensor | None = None  # [S, 2] index-space x, y
        self.index: torch.Tensor | None = None  # [S] global vertex index

    def weld(self, verts: torch.Tensor, layer: int, start: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Global index of each of a slab's ``verts`` (index space, first layer ``layer``) and which are new.

        Vertices on ``layer`` equal (bit for bit: both slabs fuse the layer by the same arithmetic)
        to one of the previous slab's top layer take its index; the others are numbered from ``start``.
        """
        n = verts.shape[0]
        new = torch.ones(n, dtype=torch.bool, device=verts.device)
        index = torch.empty(n, dtype=torch.long, device=verts.device)
        if self.xy is not None and self.xy.shape[0] and n:
            on = torch.nonzero(verts[:, 2] == float(layer)).squeeze(1)
            if on.numel():
                keys = torch.cat([self.xy, verts[on, :2]])
                _, inv = torch.unique(keys, dim=0, return_inverse=True)
                owner = torch.full((int(inv.max()) + 1,), -1, dtype=torch.long, device=verts.device)
                owner[inv[: self.xy.shape[0]]] = self.index
                match = owner[inv[self.xy.shape[0]:]]
                hit = match >= 0
                index[on[hit]] = match[hit]
                new[on[hit]] = False
        index[new] = start + torch.arange(int(new.sum()), device=verts.device)  # host sync: slab vertex count
        return index, new

    def keep(self, verts: torch.Tensor, index: torch.Tensor, layer: int) -> None:
        """Remember the vertices of a slab's top ``layer`` with their global indices."""
        top = verts[:, 2] == float(layer)
        self.xy, self.index = verts[top, :2], index[top]


def _closed_field(tsdf: wp.array, observed: wp.array, k0: int, layers: int) -> torch.Tensor:
    """The slab's TSDF with every node decided: hidden unobserved nodes (behind some view's surface,
    seen free by none) are inside (-1), the other unobserved ones outside (+1), and so is the grid's
    outer node layer (``layers`` node layers in all), so the zero level is closed."""
    t = wp.to_torch(tsdf)
    o = wp.to_torch(observed)
    field = torch.where(o == int(_k.OBS_TSDF), t, torch.where(o == int(_k.OBS_HIDDEN), -1.0, 1.0))
    field[0], field[-1], field[:, 0], field[:, -1] = 1.0, 1.0, 1.0, 1.0
    if k0 == 0:
        field[:, :, 0] = 1.0
    if k0 + field.shape[2] == layers:
        field[:, :, -1] = 1.0
    return field


def _slab_mesh(tsdf: wp.array, observed: wp.array, color: wp.array | None, k0: int, layers: int | None = None):
    """Marching cubes of one slab in index space, faces with an unobserved edge end dropped; with
    ``layers`` (the grid's node layers) the closed field of :func:`_closed_field`, every face kept.

    Returns ``(verts [V, 3] index space, faces [F, 3] int64 into verts, colours [V, 3] uint8 or None,
    seen [V] bool: both ends of the vertex's grid edge observed)`` with only the vertices the kept faces use.
    """
    from .marching_cubes import marching_cubes

    nx, ny, nz = tsdf.shape
    field = wp.to_torch(tsdf) if layers is None else _closed_field(tsdf, observed, k0, layers)
    with section("marching_cubes"):
        verts, faces = marching_cubes(field, 0.0, lower=(0.0, 0.0, float(k0)),
                                      upper=(float(nx - 1), float(ny - 1), float(k0 + nz - 1)))
    if faces.shape[0] == 0:
        return verts, faces.long(), None, torch.zeros(0, dtype=torch.bool, device=verts.device)
    # every vertex lies on one grid edge: floor and ceil of its index coordinates are the edge's ends
    # (one node when it rounded onto it, which MIN_ABS_TSDF keeps to edges with both ends observed)
    lo = torch.floor(verts).long()
    hi = torch.ceil(verts).long()
    stride = torch.tensor([ny * nz, nz, 1], device=verts.device)
    base = torch.tensor([0, 0, k0], device=verts.device)
    lo_i = ((lo - base) * stride).sum(1)
    hi_i = ((hi - base) * stride).sum(1)
    obs = wp.to_torch(observed).reshape(-1) == int(_k.OBS_TSDF)
    faces = faces.long()
    if layers is None:
        ok = obs[lo_i] & obs[hi_i]
        faces = faces[ok[faces].all(dim=1)]
    used = torch.zeros(verts.shape[0], dtype=torch.bool, device=verts.device)
    used[faces.reshape(-1)] = True
    remap = torch.cumsum(used.long(), 0) - 1
    faces = remap[faces]
    verts, lo_i, hi_i = verts[used], lo_i[used], hi_i[used]
    seen = obs[lo_i] & obs[hi_i]
    cols = None
    if color is not None:
        frac = (verts - torch.floor(verts)).sum(1, keepdim=True)  # the position along the one fractional axis
        c = wp.to_torch(color).reshape(-1, 3).float()
        c_lo, c_hi = c[lo_i], c[hi_i]
        if layers is not None:  # a closing vertex takes its observed end's colour (grey where neither is)
            grey = torch.full_like(c_lo, 128.0)
            o_lo, o_hi = obs[lo_i][:, None], obs[hi_i][:, None]
            c_lo, c_hi = (torch.where(o_lo, c_lo, torch.where(o_hi, c_hi, grey)),
                          torch.where(o_hi, c_hi, torch.where(o_lo, c_lo, grey)))
        cols = (c_lo * (1 - frac) + c_hi * frac + 0.5).clamp(0, 255).to(torch.uint8)
    return verts, faces, cols, seen


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


def fuse_tsdf(cameras: Sequence[Camera], depths: Sequence, colors: Sequence | None = None, *, lower, upper,
              voxel: float, truncation: float, far: Sequence[float] | None = None,
              device: torch.device | str | None = None, cull: bool = True,
              slab_nodes: int | None = None, close: bool = False) -> TSDFMesh:
    """Fuse z-depth maps (and colours) into a TSDF on a dense grid and extract its zero level.

    Each node of the grid is projected into every view through that camera's own lens model (pose,
    ``K`` with skew and principal point, OpenCV distortion; a distorted lens sees nothing beyond
    the field its image covers, as :func:`wtopo.fitting.depth_warp.pinhole_warp` measures it) and
    reads the depth of the pixel it falls in. A view contributes ``min(1, sdf / truncation)``
    with weight 1 when its depth is valid (``0 < d < far``) and ``sdf = (d - z) * |p| / z > -truncation``
    (``z``: the node's camera depth, ``|p|``: its distance to the camera): Open3D's
    ``ScalableTSDFVolume`` rule. The surface is the zero level of the mean, kept only where both
    nodes of each vertex's grid edge were observed by some view: open where nothing was seen.

    With ``close``, nothing is left undecided and the surface is closed (space carving): an
    unobserved node that lies deeper than the truncation behind some view's depth and that no view's
    ray crosses on its way to no surface (a pixel without depth) is inside; every other unobserved
    node (seen empty, or seen by no view) and the grid's outer node layer are outside. Where no
    view saw the surface, the mesh then closes along the boundary of the space the views saw empty,
    the tightest closure the views allow (a cup's unseen floor, the underside of an object on a rig
    above it).

    Args:
        cameras: one :class:`wtopo.Camera` per view (world frame of the grid).
        depths: per view a z-depth map [H, W] (the camera's image size), float, world units; 0 (or
            negative) marks no measurement. NumPy arrays or tensors, on any device; must be finite.
        colors: ``None``, or per view an RGB image [H, W, 3] in [0, 1] (rounded to 8 bits).
        lower: grid origin, the position of node ``(0, 0, 0)`` [3], world units.
        upper: the grid reaches at least this corner [3] (nodes up to the first at or past it).
        voxel: node spacing, world units.
        truncation: truncation distance, world units.
        far: per view a depth cut-off (depths at or beyond it are no data); ``None``: none.
        device: where to fuse (``"cpu"``, ``"cuda:N"``); ``None``: the first tensor depth's device,
            else the CPU.
        cull: skip the nodes of blocks no view's truncation band reaches (the mesh is the same
            either way; ``False`` projects every node into every view).
        slab_nodes: most nodes fused at once (memory bound); ``None``: :data:`SLAB_NODES`.
        close: close the surface by carving (above). Every node is projected (``cull`` is ignored:
            a culled block would not know whether a view saw it free).

    Returns:
        A :class:`TSDFMesh` on ``device``; zero faces (and vertices) when nothing was fused or no
        surface crosses the observed nodes. Discrete: nothing is differentiable.

    Raises:
        TypeError: a camera is not a :class:`wtopo.Camera`, a map or number has a wrong type.
        ValueError: counts or map sizes do not match the cameras, a depth or colour value is NaN or
            infinite (checked before any launch), ``upper <= lower``, ``voxel`` or ``truncation``
            not > 0, a ``far`` not > 0, ``slab_nodes`` below two node layers.

    Limitations:
        Dense in each slab: the time grows with the grid's volume where the band reaches (the block
        test skips the rest) and with the view count per node. A node reads the nearest pixel, no
        interpolation (as Open3D). Colours are averaged with the depths' weights, 8 bits per channel.

    References:
        B. Curless, M. Levoy, "A volumetric method for building complex models from range images",
        SIGGRAPH 1996. Q.-Y. Zhou, J. Park, V. Koltun, "Open3D: A modern library for 3D data
        processing", 2018 (``ScalableTSDFVolume``).
    """
    fu = _Fusion(cameras, depths, colors, lower, upper, voxel, truncation, far, device, cull and not close)
    limit = _slab_limit(slab_nodes, fu.shape)
    dev = fu.device
    empty = TSDFMesh(torch.zeros(0, 3, device=dev), torch.zeros(0, 3, dtype=torch.int32, device=dev),
                     torch.zeros(0, 3, dtype=torch.uint8, device=dev) if fu.has_color else None, fu.shape)
    if fu.n_views == 0:
        return empty
    out_v, out_f, out_c, out_s = [], [], [], []
    seam = _Seam()
    count = 0
    with fu.scope():
        for k0, tsdf, observed, color in fu.slabs(limit):
            verts, faces, cols, seen = _slab_mesh(tsdf, observed, color, k0, fu.shape[2] if close else None)
            if faces.shape[0] == 0:
                seam = _Seam()
                continue
            index, new = seam.weld(verts, k0, count)
            count += int(new.sum())  # host sync: vertex count (one per slab)
            out_v.append(verts[new])
            out_f.append(index[faces])
            if cols is not None:
                out_c.append(cols[new])
            out_s.append(seen[new])
            seam.keep(verts, index, k0 + tsdf.shape[2] - 1)
    if not out_f:
        return empty
    verts = torch.cat(out_v) * fu.voxel + torch.as_tensor(fu.lower, dtype=torch.float32, device=dev)
    faces, cols = torch.cat(out_f), (torch.cat(out_c) if fu.has_color else None)
    if close:
        verts, faces, cols = _drop_unseen_components(verts, faces, cols, torch.cat(out_s))
    return TSDFMesh(verts, faces.to(torch.int32), cols, fu.shape)


def _drop_unseen_components(verts, faces, cols, seen):
    """Keep the connected components of a closed mesh that hold a vertex of observed surface: a
    component made only of closing faces encloses space a view or two saw behind a surface and none
    saw empty (a grid corner in one view's shadow), not an object. Host round trip (SciPy)."""
    from .metrics._topology import face_components

    f = faces.cpu().numpy()
    _, label = face_components(f, verts.shape[0])
    keep = np.zeros(label.max() + 1, bool)
    keep[label[seen.cpu().numpy()[f].any(axis=1)]] = True
    keep_f = keep[label]
    if keep_f.all():
        return verts, faces, cols
    used = np.zeros(verts.shape[0], bool)
    used[f[keep_f]] = True
    f = (np.cumsum(used) - 1)[f[keep_f]]
    kv = torch.as_tensor(used, device=verts.device)
    return verts[kv], torch.as_tensor(f, device=faces.device), None if cols is None else cols[kv]


def tsdf_volume(cameras: Sequence[Camera], depths: Sequence, colors: Sequence | None = None, *, lower, upper,
                voxel: float, truncation: float, far: Sequence[float] | None = None,
                device: torch.device | str | None = None, cull: bool = True,
                slab_nodes: int | None = None) -> TSDFVolume:
    """The fused TSDF grid of :func:`fuse_tsdf` itself (same rule, same arguments), whole.

    Allocates the whole grid (8 bytes per node with colours, 5 without): for small grids, tests
    and inspection; :func:`fuse_tsdf` keeps only one slab at a time. Arguments and errors are those
    of :func:`fuse_tsdf`.

    Returns:
        A :class:`TSDFVolume` on ``device``. With ``cull``, nodes of blocks outside every view's
        truncation band read unobserved (1) even where a view saw them as free space (also 1).
    """
    fu = _Fusion(cameras, depths, colors, lower, upper, voxel, truncation, far, device, cull)
    limit = _slab_limit(slab_nodes, fu.shape)
    dev = fu.device
    tsdf = torch.ones(fu.shape, dtype=torch.float32, device=dev)
    observed = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    free = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    hidden = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    colors_out = torch.zeros(fu.shape + (3,), dtype=torch.uint8, device=dev) if fu.has_color else None
    if fu.n_views:
        with fu.scope():
            for k0, t, o, c in fu.slabs(limit):
                k1 = k0 + t.shape[2]
                tsdf[:, :, k0:k1] = wp.to_torch(t)
                state = wp.to_torch(o)
                observed[:, :, k0:k1] = state == int(_k.OBS_TSDF)
                free[:, :, k0:k1] = state == int(_k.OBS_FREE)
                hidden[:, :, k0:k1] = state == int(_k.OBS_HIDDEN)
                if c is not None:
                    colors_out[:, :, k0:k1] = wp.to_torch(c)
    return TSDFVolume(tsdf, observed, free, hidden, colors_out, fu.lower.copy(), fu.voxel)

