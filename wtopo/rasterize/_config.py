# SPDX-License-Identifier: Apache-2.0
"""The rasterizer's options (:class:`RasterConfig`), its output record (:class:`RenderOutput`) and the
argument checks :func:`wtopo.rasterize.rasterize_surfels` runs before any launch."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .._validate import require_finite, require_same_device, require_tensor
from ..camera import Camera

FILTER_SIGMA_RANGE = (0.05, 100.0)  # accepted RasterConfig.filter_sigma [pixels]


@dataclass(kw_only=True)
class RasterConfig:
    """Options of :func:`rasterize_surfels`.

    References:
        Huang et al., "2D Gaussian Splatting for Geometrically Accurate Radiance Fields", SIGGRAPH
        2024 (ray-splat intersection, low-pass fallback, depth distortion, median depth).
    """

    tile_size: int = 8
    """Tile edge in pixels (8, 16 or 32); each tile composites its own depth-sorted list. 8 measured
    1.4-1.7x faster than 16 on CPU (fewer surfels tested per pixel)."""
    max_intersections: int = 1 << 26
    """Budget of (tile, surfel) pairs; more raises ``ValueError`` before the sort (memory: 16 bytes each,
    int32 keys and surfel ids with the radix sort's second half)."""
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
    front-most surfel on depth (``wtopo.fit`` uses 0.35), at the price of
    aliasing where surfels are sparser than pixels."""
    replay: bool = True
    """CUDA: repeated calls of one shape replay a CUDA graph (see :func:`rasterize_surfels`); ``False`` renders every
    call eagerly (needed to differentiate one render twice)."""


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
    _pairs: int | None = field(default=None, repr=False)  # the (tile, surfel) pairs sorted, where read

    @property
    def near(self) -> float:
        """Near plane used (world units; a host read of :attr:`clip` when it was defaulted on the device)."""
        return self._host_clip[0] if self._host_clip is not None else float(self.clip[0])

    @property
    def far(self) -> float:
        """Far value of the distortion mapping (world units; as :attr:`near`)."""
        return self._host_clip[1] if self._host_clip is not None else float(self.clip[1])


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
    if not isinstance(config.replay, bool):
        raise TypeError(f"config.replay must be a bool, got {config.replay!r}")
    return config


def _check_values(means, quats, scales, opacities, colors_or_sh) -> None:
    """Finite surfel tensors, scales >= 0 and opacities in [0, 1], by one host read of seven reductions (a NaN or
    inf makes a sum non-finite); the indexed search that names the first bad value runs only when one fails."""
    d = {k: t.detach() for k, t in (("means", means), ("quats", quats), ("scales", scales),
                                     ("opacities", opacities), ("colors_or_sh", colors_or_sh))}
    lo, hi = torch.aminmax(d["opacities"])
    # host sync: validation only, one read for every check
    *sums, smin, olo, ohi = torch.stack([t.sum() for t in d.values()] + [d["scales"].min(), lo, hi]).tolist()
    for (nm, t), total in zip(d.items(), sums):
        if not math.isfinite(total):  # a huge finite tensor can overflow its sum: require_finite decides
            require_finite(nm, t)
    if smin < 0:
        idx = [int(v) for v in torch.nonzero(d["scales"] < 0)[0].tolist()]
        raise ValueError(f"scales must be >= 0, got {scales[tuple(idx)].item()} at index {idx}")
    if olo < 0 or ohi > 1:
        idx = int(torch.nonzero((d["opacities"] < 0) | (d["opacities"] > 1))[0])
        raise ValueError(f"opacities must lie in [0, 1], got {opacities[idx].item()} at index [{idx}]")


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
    if n:
        _check_values(means, quats, scales, opacities, colors_or_sh)
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
