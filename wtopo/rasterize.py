# SPDX-License-Identifier: Apache-2.0
"""Differentiable Gaussian-surfel rasterizer (2D Gaussian splatting) on CPU and CUDA through Warp.

Pipeline of :func:`rasterize_surfels` (kernels in ``kernels/rasterize.py`` and
``kernels/rasterize_binning.py``):

1. validation (before any launch);
2. binning (discrete, outside the tape): per-surfel tile rectangle from the footprint bound,
   one ``(tile << rank_bits | depth rank, surfel)`` pair per covered tile (int32 keys when they
   fit), Warp's stable radix sort, per-tile ranges;
3. the differentiable op through :func:`wtopo._bridge.apply`: per-surfel preparation (frame,
   projected centre, SH colour; Warp autodiff), per-pixel front-to-back compositing, and the
   explicit reverse-traversal adjoint registered with :meth:`warp.Tape.record_func`.

On CPU the pixel kernels run as interleaved tile chunks on one Python thread per core (Warp
releases the GIL); each worker accumulates per-surfel gradients and visibility counts into its
own buffer (Warp's CPU ``atomic_add`` is not atomic across threads) and the buffers are summed
afterwards in a fixed order, so reruns are bit-identical. On CUDA each pixel kernel is one launch
with real atomics, the 32 pixels of a warp walking their tile's list in step so that per-surfel
gradients and visibility counts are summed over the warp before one atomic add
(:data:`COOPERATIVE_WARPS`).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from . import _bridge
from ._profile import section
from ._validate import require_finite, require_same_device, require_tensor
from .camera import Camera
from .kernels import rasterize as _k
from .kernels import rasterize_binning as _kb

__all__ = ["RasterConfig", "RenderOutput", "rasterize_surfels", "FILTER_SIGMA_RANGE"]

FILTER_SIGMA_RANGE = (0.05, 100.0)  # accepted RasterConfig.filter_sigma [pixels]
# CUDA: the 32 pixels of a warp composite in step and sum their per-surfel gradients and visibility
# counts before one atomic add (kernels/rasterize.py, "warp-cooperative helpers"); False restores one
# atomic per pixel (the previous kernels' order of work, kept for comparison in tests and benchmarks).
# CPU launches never use it (one pixel at a time: bit-identical either way).
COOPERATIVE_WARPS = True
# With COOPERATIVE_WARPS: surfels of a tile's list fetched per step of the walk, one id load and L1 prefetch
# of its records per lane (1..32; 1: each surfel's id, then its records, loaded when it is reached).
PREFETCH_BATCH = 32


@dataclass(kw_only=True)
class RasterConfig:
    """Options of :func:`rasterize_surfels`.

    References:
        Huang et al., "2D Gaussian Splatting for Geometrically Accurate Radiance Fields", SIGGRAPH
        2024 (ray-splat intersection, low-pass fallback, depth distortion, median depth).
    """

    tile_size: int = 8
    """Tile edge in pixels (8, 16 or 32); each tile composites its own depth-sorted list. 8 measured
    1.4-1.7x faster than 16 on CPU (fewer surfels tested per pixel; benchmarks/rasterize.md)."""
    max_intersections: int = 1 << 26
    """Budget of (tile, surfel) pairs; more raises ``ValueError`` before the sort (memory: 24 bytes each)."""
    near_fraction: float = 0.05
    """Default ``near`` = this times the median z-depth of the surfel centres in front of the camera
    (2DGS uses a fixed 0.2 with cameras about 4 units away: the same ratio)."""
    far_multiple: float = 100.0
    """Default ``far`` = this times the same median depth."""
    tiles_per_chunk: int = 0
    """CPU work unit in tiles (0: about 16 chunks per worker thread)."""
    filter_sigma: float = 1.0 / math.sqrt(2.0)
    """Standard deviation of the screen-space low-pass filter [pixels]: ``rho2d = |pixel - centre|^2
    / filter_sigma^2``. The default is 2DGS's (``rho2d = 2 |pixel - centre|^2``). A narrower filter
    makes sub-pixel and edge-on surfels smaller dots: less silhouette halo and less pull of the
    front-most surfel on depth (``wtopo.fit`` uses 0.35; ``benchmarks/fit.md``), at the price of
    aliasing where surfels are sparser than pixels."""


@dataclass
class RenderOutput:
    """Images and per-surfel statistics of one rendered view (``H, W`` = camera height, width).

    Attributes:
        rgb: colour ``[H, W, 3]`` (background composited behind).
        alpha: accumulated opacity ``1 - T`` ``[H, W]``; ``alpha == 0`` marks pixels nothing
            covers (depth, median depth, normal and distortion are 0 there, with 0 gradients).
        depth: expected z-depth normalised by alpha ``[H, W]`` (0 where alpha = 0).
        median_depth: z-depth of the contribution where transmittance crosses 0.5 (the last one
            if it never does; 0 where nothing contributes) ``[H, W]``.
        normal: alpha-weighted sum of the world-frame unit normals, each flipped to face the camera,
            ``[H, W, 3]`` (divide by ``alpha`` for a unit-ish normal).
        distortion: 2DGS depth distortion ``sum_{i>j} w_i w_j (m_i - m_j)^2`` with
            ``m = far / (far - near) * (1 - near / z)`` ``[H, W]``.
        visibility: int32 ``[N]``, number of pixels each surfel contributed to (discrete).
        radii: int32 ``[N]``, screen radius bound in pixels (0: culled or off-screen; discrete).
        means2d: projected centres in pixels ``[N, 2]`` (lens distortion applied), a leaf that
            requires grad whenever an input does; after backward its ``.grad`` is ``dL/d(shift)``
            for a screen-space translation ``shift`` of each surfel's whole footprint, taken at 0
            (the densification statistic): the filter branch sees ``pixel - (centre + shift)``,
            the object-space branch the ray through ``pixel - shift`` (pinhole intrinsics; exact
            without lens distortion). The value of this tensor is never read by the op.
        clip: ``(near, far)`` used, float64 [2] on the device (see :attr:`near`, :attr:`far`).
        overflow: ``None``, except from the fit's deferred-count path (``_rasterize_trusted`` with
            ``defer_count``): a bool scalar on the device, ``True`` when the view had more
            (tile, surfel) pairs than the buffers sized from earlier calls held, so the images are
            incomplete and the caller must render it again.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    median_depth: torch.Tensor
    normal: torch.Tensor
    distortion: torch.Tensor
    visibility: torch.Tensor
    radii: torch.Tensor
    means2d: torch.Tensor
    clip: torch.Tensor
    overflow: torch.Tensor | None = None
    _host_clip: tuple[float, float] | None = field(default=None, repr=False)

    @property
    def near(self) -> float:
        """Near plane used (world units; a host read of :attr:`clip` when it was defaulted on the device)."""
        return self._host_clip[0] if self._host_clip is not None else float(self.clip[0])

    @property
    def far(self) -> float:
        """Far value of the distortion mapping (world units; as :attr:`near`)."""
        return self._host_clip[1] if self._host_clip is not None else float(self.clip[1])


# -- validation ------------------------------------------------------------------------------


def _validate_config(config: RasterConfig | None) -> RasterConfig:
    """Check a :class:`RasterConfig` (``None``: the defaults) and return it."""
    if config is None:
        config = RasterConfig()
    elif not isinstance(config, RasterConfig):
        raise TypeError(f"config must be a RasterConfig or None, got {type(config).__name__}")
    if config.tile_size not in (8, 16, 32):
        raise ValueError(f"config.tile_size must be 8, 16 or 32, got {config.tile_size!r}")
    if not (isinstance(config.max_intersections, int) and 0 < config.max_intersections < 2**31):
        raise ValueError(f"config.max_intersections must be an int in [1, 2^31 - 1], got {config.max_intersections!r}")
    for nm in ("near_fraction", "far_multiple"):
        v = getattr(config, nm)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"config.{nm} must be a finite number > 0, got {v!r}")
    if config.near_fraction >= config.far_multiple:
        raise ValueError(f"config.near_fraction ({config.near_fraction}) must be < config.far_multiple "
                         f"({config.far_multiple})")
    fs = config.filter_sigma
    lo, hi = FILTER_SIGMA_RANGE
    if not (isinstance(fs, (int, float)) and not isinstance(fs, bool) and math.isfinite(fs) and lo <= fs <= hi):
        raise ValueError(f"config.filter_sigma must be a number of pixels in [{lo}, {hi}], got {fs!r}")
    if not (isinstance(config.tiles_per_chunk, int) and config.tiles_per_chunk >= 0):
        raise ValueError(f"config.tiles_per_chunk must be an int >= 0, got {config.tiles_per_chunk!r}")
    return config


def _validate(means, quats, scales, opacities, colors_or_sh, camera, sh_degree, background, near, far, config):
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a wtopo.Camera, got {type(camera).__name__}")
    config = _validate_config(config)
    require_tensor("means", means, shape=(None, 3))
    n = means.shape[0]
    require_tensor("quats", quats, shape=(n, 4))
    require_tensor("scales", scales, shape=(n, 2))
    require_tensor("opacities", opacities, shape=(n,))
    if not isinstance(colors_or_sh, torch.Tensor):
        raise TypeError(f"colors_or_sh must be a torch.Tensor, got {type(colors_or_sh).__name__}")
    if colors_or_sh.ndim == 2:
        require_tensor("colors_or_sh", colors_or_sh, shape=(n, 3))
        if sh_degree is not None:
            raise ValueError(f"sh_degree must be None for [N, 3] colours, got {sh_degree!r}")
    else:
        require_tensor("colors_or_sh", colors_or_sh, shape=(n, None, 3))
        k = colors_or_sh.shape[1]
        if sh_degree is None:
            deg = int(round(math.sqrt(k))) - 1
            if (deg + 1) ** 2 != k or not 0 <= deg <= 3:
                raise ValueError(f"colors_or_sh with K = {k} coefficients is not a full SH band set (1, 4, 9, 16); "
                                 f"pass sh_degree")
            sh_degree = deg
        elif isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be an int in [0, 3], got {sh_degree!r}")
        elif (sh_degree + 1) ** 2 > k:
            raise ValueError(f"sh_degree {sh_degree} needs {(sh_degree + 1) ** 2} coefficients, colors_or_sh has {k}")
    dtype = means.dtype
    for nm, t in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors_or_sh", colors_or_sh)):
        if t.dtype != dtype:
            raise TypeError(f"{nm} must have the dtype of means ({dtype}), got {t.dtype}")
    device = require_same_device(means=means, quats=quats, scales=scales, opacities=opacities,
                                 colors_or_sh=colors_or_sh)
    for nm, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                  ("colors_or_sh", colors_or_sh)):
        # one reduction first (a NaN/inf makes the sum non-finite); the indexed search only when it is
        if t.numel() and not bool(torch.isfinite(t.detach().sum())):  # host sync: validation only
            require_finite(nm, t.detach())
    if n:
        if float(scales.detach().min()) < 0:  # host sync: validation only
            idx = [int(v) for v in torch.nonzero(scales.detach() < 0)[0].tolist()]
            raise ValueError(f"scales must be >= 0, got {scales[tuple(idx)].item()} at index {idx}")
        lo, hi = torch.aminmax(opacities.detach())
        if float(lo) < 0 or float(hi) > 1:  # host sync: validation only
            idx = int(torch.nonzero((opacities.detach() < 0) | (opacities.detach() > 1))[0])
            raise ValueError(f"opacities must lie in [0, 1], got {opacities[idx].item()} at index [{idx}]")
    if background is None:
        bg = torch.zeros(3, dtype=dtype, device=device)
    else:
        bg = torch.as_tensor(background, dtype=dtype, device=device).detach()
        if bg.shape != (3,):
            raise ValueError(f"background must have shape [3], got {list(bg.shape)}")
        require_finite("background", bg)
    for nm, v in (("near", near), ("far", far)):
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        if v is not None and not ok:
            raise ValueError(f"{nm} must be a finite number > 0 or None, got {v!r}")
    if near is not None and far is not None and not near < far:
        raise ValueError(f"near must be < far, got near={near}, far={far}")
    return config, sh_degree, bg, device


# -- camera tables ---------------------------------------------------------------------------


def _camera_tables(camera: Camera, device, dtype, tile_size: int):
    """Rays [H, W, 3] and per-tile-column / per-tile-row normalised-coordinate ranges (cached on the camera)."""
    return camera.cached(("wtopo.rasterize.tables", str(device), dtype, tile_size),
                         lambda: _build_camera_tables(camera, device, dtype, tile_size))


def _build_camera_tables(camera: Camera, device, dtype, tile_size: int):
    """What :func:`_camera_tables` caches."""
    _, dirs = camera.pixel_rays(device, dtype)
    d_cam = dirs.detach().cpu().double().numpy() @ camera.R.T
    h, w = camera.height, camera.width
    tx, ty = -(-w // tile_size), -(-h // tile_size)
    x = d_cam[..., 0]
    y = d_cam[..., 1]
    colx_min = np.array([x[:, j * tile_size:(j + 1) * tile_size].min() for j in range(tx)])
    colx_max = np.array([x[:, j * tile_size:(j + 1) * tile_size].max() for j in range(tx)])
    rowy_min = np.array([y[i * tile_size:(i + 1) * tile_size].min() for i in range(ty)])
    rowy_max = np.array([y[i * tile_size:(i + 1) * tile_size].max() for i in range(ty)])
    # binary searches need non-decreasing tables; a lens that folds the image gets full ranges
    if np.any(np.diff(colx_min) < 0) or np.any(np.diff(colx_max) < 0):
        colx_min[:], colx_max[:] = -np.inf, np.inf
    if np.any(np.diff(rowy_min) < 0) or np.any(np.diff(rowy_max) < 0):
        rowy_min[:], rowy_max[:] = -np.inf, np.inf
    wdev = _bridge.warp_device(device)
    tables = tuple(wp.array(a, dtype=wp.float64, device=wdev) for a in (colx_min, colx_max, rowy_min, rowy_max))
    return dirs, tables


def _depth_row(camera: Camera, device, dtype) -> torch.Tensor:
    """Third row of the world-to-camera rotation [3] on the device (cached on the camera: no copy per call)."""
    return camera.cached(("wtopo.rasterize.depth_row", str(device), dtype),
                         lambda: torch.as_tensor(camera.R[2], dtype=dtype, device=device))


def _camera_record(camera: Camera, clip: torch.Tensor, dtype, filter_sigma: float):
    """Everything the kernels read per view, as a :class:`wtopo.kernels.rasterize.CameraRecord` of the op dtype.

    Values are computed in float64 on the host and rounded once to the op dtype when assigned;
    ``clip`` ([near, far] of the op dtype on the device) is referenced, not copied.
    """
    rec = _k.CAMERA[wp.float64 if dtype == torch.float64 else wp.float32]()
    fx, skew, cx = (float(v) for v in camera.K[0])
    dist = camera.distortion if camera.distortion is not None else np.zeros(5)
    rec.R = type(rec.R)(*(float(v) for v in camera.R.reshape(-1)))
    rec.t = type(rec.t)(*(float(v) for v in camera.t))
    rec.center = type(rec.center)(*(float(v) for v in camera.center))
    rec.fx, rec.fy, rec.cx, rec.cy, rec.skew = fx, float(camera.K[1, 1]), cx, float(camera.K[1, 2]), skew
    rec.k1, rec.k2, rec.p1, rec.p2, rec.k3 = (float(v) for v in dist)
    rec.clip = _bridge.to_warp(clip)
    rec.filter_inv_sq = 1.0 / float(filter_sigma) ** 2
    rec.width, rec.height = int(camera.width), int(camera.height)
    return rec


def _default_clip(means: torch.Tensor, camera: Camera, near, far, config: RasterConfig):
    if near is not None and far is not None:
        return float(near), float(far)
    z = means.detach() @ _depth_row(camera, means.device, means.dtype) + float(camera.t[2])
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
    n = means.shape[0]
    if n == 0:
        return _clip_from_host(config.near_fraction, config.far_multiple, means.device)
    z = means.detach() @ _depth_row(camera, means.device, means.dtype) + float(camera.t[2])
    pos = z > 0
    k = pos.sum()
    zs = torch.where(pos, z, torch.full_like(z, math.inf)).sort().values
    zref = torch.where(k > 0, zs.gather(0, ((k - 1).clamp_min(0) // 2).view(1)), torch.ones_like(zs[:1])).double()
    return torch.cat([zref * config.near_fraction, zref * config.far_multiple])


# -- CPU work distribution ------------------------------------------------------------------

_compiled: set = set()
_compile_lock = threading.Lock()


def _launch_tiles(kernel, n_tiles: int, tile_px: int, inputs: list, outputs: list, *, device, workers: int,
                  tiles_per_chunk: int) -> None:
    """Launch a per-pixel kernel ``(offset, worker, ...)`` over tiles, in chunks spread over ``workers`` threads."""
    if n_tiles <= 0:
        return
    key = (kernel.key, str(device), tuple(getattr(a, "dtype", type(a)) for a in (*inputs, *outputs)))
    if workers <= 1:
        wp.launch(kernel, dim=n_tiles * tile_px, inputs=[0, 0, *inputs], outputs=outputs, device=device,
                  record_tape=False)
        return
    chunk = tiles_per_chunk or max(1, n_tiles // (16 * workers))
    n_chunks = -(-n_tiles // chunk)

    def work(w: int) -> None:
        # static interleaved assignment: balanced for spatially clustered cost, and each worker's
        # buffer always sums the same chunks in the same order (bit-identical reruns)
        for c in range(w, n_chunks, workers):
            lo, hi = c * chunk, min(n_tiles, (c + 1) * chunk)
            wp.launch(kernel, dim=(hi - lo) * tile_px, inputs=[lo * tile_px, w, *inputs], outputs=outputs,
                      device=device, record_tape=False)

    if key not in _compiled:
        with _compile_lock:  # the first launch compiles: never from two threads at once
            for w in range(workers):  # same chunk-to-worker assignment as the threaded path: same sums
                work(w)
            _compiled.add(key)
        return
    futures = [_bridge._get_pool(workers).submit(work, w) for w in range(workers)]  # noqa: SLF001
    for f in futures:
        f.result()


def _num_workers(wdev, n_tiles: int) -> int:
    if not wdev.is_cpu:
        return 1  # CUDA: one launch, real atomics
    return max(1, min(_bridge.cpu_threads(), n_tiles))


# -- binning ---------------------------------------------------------------------------------


@dataclass
class _Bins:
    tile_start: wp.array
    tile_end: wp.array
    ids: wp.array
    radii: torch.Tensor
    means2d: torch.Tensor
    cutoff: wp.array
    overflow: torch.Tensor | None = None


_CAPACITY_HEADROOM = 1.25  # deferred path: sort buffers hold this times the largest recent pair count ...
_CAPACITY_MIN = 4096  # ... and at least this many pairs
_CAPACITY_SHRINK = 4.0  # shrink once a count falls below 1 / this of the capacity (after fewer surfels)
_PENDING_MAX = 8  # device counts in flight at most (pinned host copies)


class _PairCapacity:
    """Number of (tile, surfel) pairs the deferred-count binning sizes its sort for, kept per device.

    Every deferred call posts its pair count into pinned host memory with a non-blocking copy and an
    event; later calls read the counts whose events have completed, so no call waits for the device.
    """

    def __init__(self):
        self.value = 0
        self.pending: deque = deque()

    def observe(self, total: int, limit: int) -> None:
        """Fit the capacity to a measured pair count (grow above it, shrink when far below)."""
        if total > self.value or total * _CAPACITY_SHRINK < self.value:
            self.value = min(limit, max(_CAPACITY_MIN, math.ceil(total * _CAPACITY_HEADROOM)))

    def post(self, total: torch.Tensor, limit: int) -> None:
        """Queue a device pair count (int64 scalar tensor) to be observed once the device has it."""
        if not total.is_cuda:
            self.observe(int(total), limit)  # CPU: the value is already there, reading it costs nothing
            return
        if len(self.pending) >= _PENDING_MAX:
            return
        host = torch.empty((), dtype=torch.int64, pin_memory=True)
        host.copy_(total, non_blocking=True)
        event = torch.cuda.Event()
        event.record()
        self.pending.append((event, host, limit))

    def poll(self) -> None:
        """Observe the posted counts that have arrived (never blocks)."""
        while self.pending and self.pending[0][0].query():
            _, host, limit = self.pending.popleft()
            self.observe(int(host), limit)


_capacities: dict[str, _PairCapacity] = {}


def _pair_capacity(wdev) -> _PairCapacity:
    return _capacities.setdefault(str(wdev), _PairCapacity())


def _bin(means, quats, scales, opacities, cam_rec, tables, camera: Camera, config: RasterConfig, wdev, *,
         defer_count: bool = False) -> _Bins:
    """Tile ranges and depth-sorted surfel ids per tile.

    With ``defer_count`` the sort buffers are sized from :class:`_PairCapacity` (counts of earlier
    calls) instead of this call's count, so nothing waits for the device; pairs beyond the capacity
    are dropped and ``overflow`` says so (a device flag). Without it the count is read (one host
    sync) and the result is always complete.
    """
    n = means.shape[0]
    ts = config.tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles = tiles_x * tiles_y
    dt = _bridge.float_dtype(means)
    rect = wp.empty(n, dtype=wp.vec4i, device=wdev)
    counts = wp.empty(n, dtype=wp.int32, device=wdev)
    radii = wp.empty(n, dtype=wp.int32, device=wdev)
    means2d = wp.empty(n, dtype=_bridge.vec_dtype(means, 2), device=wdev)
    cutoff = wp.empty(n, dtype=dt, device=wdev)
    inputs = [_bridge.to_warp(means, _bridge.vec_dtype(means, 3)), _bridge.to_warp(quats, _bridge.vec_dtype(quats, 4)),
              _bridge.to_warp(scales, _bridge.vec_dtype(scales, 2)), _bridge.to_warp(opacities, dt), cam_rec, *tables,
              ts]
    capacity = _pair_capacity(wdev)
    overflow = None
    with section("rasterize_binning"):
        _bridge.launch_split(_kb.bin_surfels_kernel, n, inputs, [rect, counts, radii, means2d, cutoff], device=wdev)
        counts_t = wp.to_torch(counts)
        csum = torch.cumsum(counts_t, 0, dtype=torch.int64)
        defer = defer_count and n > 0
        if defer:
            capacity.poll()
            if capacity.value == 0:  # host sync: once per device, the first count sizes the capacity
                capacity.observe(int(csum[-1]), config.max_intersections)
            total = capacity.value  # pairs sorted: the real ones, then padding keys after every tile
            overflow = csum[-1] > total
            capacity.post(csum[-1], config.max_intersections)
        else:
            total = int(csum[-1]) if n else 0  # host sync: the intersection count sizes the sort buffers
            if total <= config.max_intersections:
                capacity.observe(total, config.max_intersections)
    if total > config.max_intersections:
        raise ValueError(f"rasterize_surfels: {n} surfels cover {total} (tile, surfel) pairs, above "
                         f"config.max_intersections = {config.max_intersections}; raise the budget, use a larger "
                         f"tile_size, or prune/shrink large surfels")
    tile_start = wp.zeros(n_tiles, dtype=wp.int32, device=wdev)
    tile_end = wp.zeros(n_tiles, dtype=wp.int32, device=wdev)
    rank_bits = max(1, (n - 1).bit_length())
    # deferred: one more tile value for the padding keys (tile n_tiles), sorted after every real pair
    key_bits = rank_bits + max(1, (n_tiles if defer else n_tiles - 1).bit_length())
    keys = wp.empty(max(2 * total, 1), dtype=wp.int32 if key_bits <= 31 else wp.int64, device=wdev)
    values = wp.empty(max(2 * total, 1), dtype=wp.int32, device=wdev)
    if total:
        with section("rasterize_sort"):
            # depth rank of every surfel (Warp's stable radix sort on the centre z-depths)
            zc = torch.empty(2 * n, dtype=means.dtype, device=means.device)
            zc[:n] = means.detach() @ _depth_row(camera, means.device, means.dtype)
            order = torch.empty(2 * n, dtype=torch.int32, device=means.device)
            order[:n] = torch.arange(n, dtype=torch.int32, device=means.device)
            wp.utils.radix_sort_pairs(_bridge.to_warp(zc), _bridge.to_warp(order), n)
            rank = torch.empty(n, dtype=torch.int64, device=means.device)
            rank[order[:n].long()] = torch.arange(n, dtype=torch.int64, device=means.device)
        with section("rasterize_binning"):
            if defer:
                keys[:total].fill_(n_tiles << rank_bits)
            offsets = csum - counts_t
            if defer:  # pairs past the capacity are dropped: keep the offsets (int32) at most there
                offsets = offsets.clamp_max(total)
            offsets = offsets.to(torch.int32)
            _bridge.launch_split(_kb.emit_intersections_kernel, n,
                                 [rect, _bridge.to_warp(offsets), _bridge.to_warp(rank), tiles_x, rank_bits, total],
                                 [keys, values],
                                 device=wdev)
        with section("rasterize_sort"):
            wp.utils.radix_sort_pairs(keys, values, total, end_bit=key_bits)
        with section("rasterize_binning"):
            _bridge.launch_split(_kb.tile_ranges_kernel, total, [keys, total, rank_bits], [tile_start, tile_end],
                                 device=wdev)
    return _Bins(tile_start, tile_end, values, wp.to_torch(radii), wp.to_torch(means2d), cutoff, overflow)


# -- the differentiable op -------------------------------------------------------------------


def _make_run(bins: _Bins, rays: torch.Tensor, cam_rec, bg_wp, sh_degree: int, camera: Camera, config, wdev, dtype):
    ts = config.tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles = tiles_x * tiles_y
    h, w = camera.height, camera.width
    workers = _num_workers(wdev, n_tiles)
    s = wp.float64 if dtype == torch.float64 else wp.float32
    v2, v3 = (wp.vec2d, wp.vec3d) if dtype == torch.float64 else (wp.vec2, wp.vec3)
    rays_wp = _bridge.to_warp(rays, v3)
    coop = int(COOPERATIVE_WARPS and not wdev.is_cpu)
    batch = PREFETCH_BATCH if coop else 1  # a batch is spread over the lanes of a warp

    def run(means, quats, scales, opacities, sh, means2d):
        n = means.shape[0]
        with section("rasterize_forward"):
            prep = [wp.empty(n, dtype=t, device=wdev, requires_grad=True) for t in (v3, v3, v3, v3, v3, v2, s, v3)]
            uax, vax, nrm, auv, nrm_face, m2, zc, color = prep
            _bridge.launch_split(_k.prepare_surfels_kernel, n, [means, quats, scales, sh, cam_rec, sh_degree], prep,
                                 device=wdev, record_tape=True)
            outs = [wp.empty((h, w), dtype=t, device=wdev, requires_grad=True) for t in (v3, s, s, s, v3, s)]
            rgb, alpha, depth, median, normal, dist = outs
            t_final = wp.empty((h, w), dtype=s, device=wdev)
            sums = wp.empty((h, w), dtype=v3, device=wdev)
            last = wp.empty((h, w), dtype=wp.int32, device=wdev)
            median_idx = wp.empty((h, w), dtype=wp.int32, device=wdev)
            visibility = wp.zeros(n, dtype=wp.int32, device=wdev) if workers == 1 else None
            # one worker (CUDA): the kernel counts straight into the output, no per-worker buffer to sum
            vis_w = visibility.reshape((1, n)) if workers == 1 else wp.zeros((workers, n), dtype=wp.int32, device=wdev)
            geo = wp.empty(n, dtype=_k.SURFEL[s], device=wdev)
            _bridge.launch_split(_k.pack_surfels_kernel, n, [uax, vax, nrm, auv, m2, zc, bins.cutoff], [geo],
                                 device=wdev)
            surf = [geo, nrm_face, color, opacities, bg_wp, ts, tiles_x, coop, batch]
            _launch_tiles(_k.render_forward_kernel, n_tiles, ts * ts,
                          [bins.tile_start, bins.tile_end, bins.ids, rays_wp, cam_rec, *surf],
                          [*outs, t_final, sums, last, median_idx, vis_w], device=wdev, workers=workers,
                          tiles_per_chunk=config.tiles_per_chunk)
            if workers > 1:
                visibility = wp.empty(n, dtype=wp.int32, device=wdev)
                _bridge.launch_split(_kb.sum_visibility_kernel, n, [vis_w], [visibility], device=wdev)

        # gradient order: uax, vax, nrm, auv, nrm_face, m2, zc, color, opacity, shift
        grad_types = (v3, v3, v3, v3, v3, v2, s, v3, s, v2)

        def backward():
            with section("rasterize_backward"):
                def grad_or_empty(a, t):
                    return a.grad if a.requires_grad else wp.zeros(0, dtype=t, device=wdev)

                targets = [*(a.grad for a in prep), grad_or_empty(opacities, s), grad_or_empty(means2d, v2)]
                if workers == 1:
                    # one worker (CUDA): accumulate straight into the tape's zeroed gradient arrays (same sums
                    # as a zeroed buffer added to them), no buffers to clear and no reduction launch
                    bufs = [g.reshape((1, n)) if g.shape[0] else wp.zeros((1, n), dtype=t, device=wdev)
                            for g, t in zip(targets, grad_types)]
                else:
                    bufs = [wp.zeros((workers, n), dtype=t, device=wdev) for t in grad_types]
                _launch_tiles(_k.render_backward_kernel, n_tiles, ts * ts,
                              [bins.tile_start, bins.ids, rays_wp, cam_rec, *surf, t_final, sums, last, median_idx,
                               *(o.grad for o in outs)],
                              bufs, device=wdev, workers=workers, tiles_per_chunk=config.tiles_per_chunk)
                if workers > 1:
                    _bridge.launch_split(_k.reduce_gradients_kernel, n, bufs, targets, device=wdev)

        tape = _bridge.active_tape()
        if tape is not None and n > 0:  # N = 0: nothing to differentiate (empty arrays have no grad buffer)
            tape.record_func(backward, [*outs, *prep, *(a for a in (opacities, means2d) if a.requires_grad)])
        return (*outs, visibility)

    return run


def rasterize_surfels(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      colors_or_sh: torch.Tensor, camera: Camera, *, sh_degree: int | None = None,
                      background=None, near: float | None = None, far: float | None = None,
                      config: RasterConfig | None = None) -> RenderOutput:
    """Render Gaussian surfels (2D Gaussians) seen by one camera, differentiably.

    Each pixel's ray (:meth:`wtopo.Camera.pixel_rays`, so OpenCV distortion is exact) is
    intersected with each surfel's plane; the local coordinates ``(u, v)`` in units of the scales
    give ``rho3d = u^2 + v^2``; the screen-space low-pass ``rho2d = |pixel - centre|^2 /
    config.filter_sigma^2`` (2DGS: ``2 |pixel - centre|^2``) takes over for tiny or edge-on
    surfels: ``rho = min(rho3d, rho2d)`` (the object-space value while ``rho3d <= rho2d + 1e-9``,
    so rounding cannot pick the branch at the centre ray), ``alpha = min(0.99, opacity *
    exp(-rho / 2))``. Contributions with ``alpha < 1/255`` or a z-depth below ``near`` (the
    intersection depth, or the centre depth in the filter branch) are skipped; compositing runs
    front to back in the order of the centres' z-depth, per tile (8x8 pixels by default), and
    stops before the transmittance would fall below 1e-4.

    Args:
        means: surfel centres [world units], shape [N, 3], float32 or float64.
        quats: rotations ``(w, x, y, z)`` of any norm, shape [N, 4]; local +z is the normal,
            local x/y the tangent axes. A quaternion with ``|q|^2 < 1e-30`` is taken as the
            identity (its gradient is then 0).
        scales: tangent standard deviations [world units], linear, shape [N, 2], >= 0 (clamped
            to >= 1e-30; tiny surfels render through the screen-space filter).
        opacities: in [0, 1], shape [N].
        colors_or_sh: RGB colours [N, 3] (used as is), or SH coefficients [N, K, 3] (3DGS
            convention: colour = max(SH(view dir) + 0.5, 0)).
        camera: the view; its ``width x height`` sets the image size.
        sh_degree: SH degree 0..3 (default: from K); must be None for [N, 3] colours.
        background: RGB [3] composited behind (not differentiable; default black).
        near: near plane (z-depth, world units). Default: ``config.near_fraction`` times the
            median z-depth of the centres in front of the camera (scale-free; a host sync).
            Surfels with centre depth <= near are culled.
        far: far value of the distortion mapping (default ``config.far_multiple`` times that
            median); it does not cull.
        config: :class:`RasterConfig`.

    Returns:
        :class:`RenderOutput` of the dtype and device of ``means``. ``rgb``, ``alpha``,
        ``depth``, ``median_depth``, ``normal`` and ``distortion`` are differentiable w.r.t.
        ``means``, ``quats``, ``scales``, ``opacities`` and ``colors_or_sh`` (the compositing
        order, the branch choice and the skips are discrete); ``visibility`` and ``radii`` are
        discrete; ``means2d.grad`` receives the screen-space gradient.

    Raises:
        TypeError: wrong types or dtypes.
        ValueError: wrong shapes, NaN/inf (naming the first index), negative scales, opacities
            outside [0, 1], invalid near/far/sh_degree, or more tile intersections than
            ``config.max_intersections``.

    Limitations:
        The compositing order is per tile by centre depth (as 2DGS), not per pixel. A surfel
        whose disk reaches the camera plane is binned to every tile. Lens models whose
        normalised coordinates are not monotone across the image bin every surfel to all
        tiles (correct, slower). The backward pass allocates one gradient buffer per CPU worker.

    References:
        Huang et al., "2D Gaussian Splatting for Geometrically Accurate Radiance Fields", 2024.
        Kerbl et al., "3D Gaussian Splatting for Real-Time Radiance Field Rendering", 2023.
    """
    config, sh_degree, bg, device = _validate(means, quats, scales, opacities, colors_or_sh, camera, sh_degree,
                                              background, near, far, config)
    near, far = _default_clip(means, camera, near, far, config)
    return _render(means, quats, scales, opacities, colors_or_sh, camera, sh_degree, bg,
                   _clip_from_host(near, far, device), config, host_clip=(near, far), defer_count=False)


def _rasterize_trusted(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                       colors_or_sh: torch.Tensor, camera: Camera, *, sh_degree: int | None,
                       background: torch.Tensor, config: RasterConfig, defer_count: bool = False,
                       device_clip: bool | None = None) -> RenderOutput:
    """:func:`rasterize_surfels` without argument checks, for callers whose tensors are checked already.

    The fit's renderer calls this every iteration: its surfel tensors are its own (finite by its
    guards, scales and opacities from ``exp`` / ``sigmoid``), ``background`` is a [3] tensor on
    their device and ``config`` was validated once. Nothing here reads the device: the default
    near / far planes are computed on the device when ``device_clip`` (default: on CUDA; on CPU the
    host median is faster and equal), and with ``defer_count`` the (tile, surfel) pair count is not
    read either (see :func:`_bin`): the caller must check :attr:`RenderOutput.overflow` (for
    instance with the loss it reads anyway) and render again when it is set. Same results as
    :func:`rasterize_surfels` otherwise (bit for bit).
    """
    device = means.device
    if device_clip is None:
        device_clip = device.type == "cuda"
    if device_clip:
        clip, host = _default_clip_device(means, camera, config), None
    else:
        host = _default_clip(means, camera, None, None, config)
        clip = _clip_from_host(*host, device)
    if colors_or_sh.ndim == 3 and sh_degree is None:
        sh_degree = int(round(math.sqrt(colors_or_sh.shape[1]))) - 1
    return _render(means, quats, scales, opacities, colors_or_sh, camera, sh_degree, background.detach(), clip,
                   config, host_clip=host, defer_count=defer_count)


def _render(means, quats, scales, opacities, colors_or_sh, camera: Camera, sh_degree, bg: torch.Tensor,
            clip: torch.Tensor, config: RasterConfig, *, host_clip, defer_count: bool) -> RenderOutput:
    """The op after validation; ``clip`` = ``[near, far]`` float64 [2] on the device."""
    dtype = means.dtype
    device = means.device
    wdev = _bridge.warp_device(device)
    rays, tables = _camera_tables(camera, device, dtype, config.tile_size)
    cam_rec = _camera_record(camera, clip.to(dtype), dtype, config.filter_sigma)
    with _bridge.torch_stream(wdev, device):
        bins = _bin(means, quats, scales, opacities, cam_rec, tables, camera, config, wdev, defer_count=defer_count)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, scales, opacities,
                                                                           colors_or_sh))
    means2d = bins.means2d.clone().requires_grad_(needs_grad)
    if colors_or_sh.ndim == 2:
        sh = colors_or_sh.unsqueeze(1)
        deg = -1
    else:
        sh = colors_or_sh[:, : (sh_degree + 1) ** 2]
        deg = sh_degree
    v3 = _bridge.vec_dtype(means, 3)
    bg_t = bg.reshape(1, 3)
    run = _make_run(bins, rays, cam_rec, _bridge.to_warp(bg_t, v3), deg, camera, config, wdev, dtype)
    op = _bridge.WarpOp(
        "rasterize_surfels", run,
        in_dtypes=(v3, _bridge.vec_dtype(means, 4), _bridge.vec_dtype(means, 2), _bridge.float_dtype(means), v3,
                   _bridge.vec_dtype(means, 2)),
        differentiable_inputs=(True,) * 6,
        differentiable_outputs=(True,) * 6 + (False,),
    )
    rgb, alpha, depth, median, normal, dist, vis = _bridge.apply(op, means, quats, scales, opacities, sh, means2d)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                        visibility=vis, radii=bins.radii, means2d=means2d, clip=clip, overflow=bins.overflow,
                        _host_clip=host_clip)
