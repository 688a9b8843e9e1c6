# SPDX-License-Identifier: Apache-2.0
"""Differentiable Gaussian-surfel rasterizer (2D Gaussian splatting) on CPU and CUDA through Warp.

Pipeline of :func:`rasterize_surfels` (kernels in ``kernels/rasterize.py``,
``kernels/rasterize_backward.py``, ``kernels/rasterize_tiles.py`` and ``kernels/rasterize_binning.py``):

1. validation (before any launch);
2. binning (discrete, outside the tape): per-surfel tile rectangle from the footprint bound,
   the surfels' depth order (a radix sort of their centre depths), one ``(tile, surfel)`` pair per covered
   tile written in that order, a stable radix sort of the pairs by tile (which keeps each tile front to
   back), per-tile ranges;
3. the differentiable op through :func:`wtopo._bridge.apply`: per-surfel preparation (frame,
   projected centre, SH colour; Warp autodiff), per-pixel front-to-back compositing, and the
   explicit reverse-traversal adjoint registered with :meth:`warp.Tape.record_func`.

On CPU the pixel kernels are per tile (``kernels/rasterize_tiles.py``): one thread walks a tile's
list once and each surfel visits only the pixels of its pixel rectangle (written by the binning), the
same arithmetic per pixel as the per-pixel kernels, bit for bit. Interleaved tile chunks run on one
Python thread per core (one launch each; Warp releases the GIL); each worker accumulates per-surfel
gradients and visibility counts into its own buffer (Warp's CPU ``atomic_add`` is not atomic across
threads) and the buffers are summed afterwards in a fixed order, so reruns are bit-identical. On
CUDA each pixel kernel is one launch with real atomics, the 32 pixels of a warp walking their tile's
list in step so that per-surfel gradients and visibility counts are summed over the warp before one atomic add
(``_run.COOPERATIVE_WARPS``).

Modules (private; import from ``wtopo.rasterize``):

* ``_config``: :class:`RasterConfig`, :class:`RenderOutput` and the argument checks;
* ``_camera``: pixel rays, tile tables, the kernels' camera record (a one-element array in device memory, a copy
  per call) and the default clip planes;
* ``_binning``: tile binning and depth sort, and the deferred path's pair capacity;
* ``_run``: the forward and backward launches of the differentiable op (CPU tile workers);
* ``_graphable``: the render as a function of tensors alone, the camera included (the CUDA graphs of the fit,
  :mod:`wtopo.fitting.raster_graph`, and of repeated public calls);
* ``_replay``: repeated calls of :func:`rasterize_surfels` of one shape replayed as CUDA graphs.
"""

from __future__ import annotations

import math

import torch

from .. import _bridge
from ..camera import Camera
from . import _replay
from ._binning import _bin
from ._camera import _camera_record, _camera_tables, _clip_from_host, _default_clip, _default_clip_device
from ._config import FILTER_SIGMA_RANGE, RasterConfig, RenderOutput, _validate
from ._run import _apply_op

__all__ = ["RasterConfig", "RenderOutput", "rasterize_surfels", "FILTER_SIGMA_RANGE"]


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

    Repeated calls:
        On CUDA, after two calls of one shape (surfel count, colour layout, image size, settings, which inputs
        require grad) with both clip planes defaulted, that shape's op is captured as a CUDA graph and later calls
        replay it: the same values, two host reads a call (the argument checks, then the pair count), outputs
        and gradients that are the caller's own copies. A call no gradient can reach replays the forward alone,
        reading the surfel tensors where they lie while the caller keeps passing tensors at the same addresses
        (parameters updated in place), else copying them in. A call made while an earlier replay of its shape still
        awaits its backward renders eagerly; a replayed render is differentiated once (a second backward raises;
        ``RasterConfig(replay=False)`` renders every call eagerly). ``wtopo.rasterize._replay`` has the details.

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

    def eager(near=near, far=far) -> RenderOutput:
        near, far = _default_clip(means, camera, near, far, config)
        return _render(means, quats, scales, opacities, colors_or_sh, camera, sh_degree, bg,
                       _clip_from_host(near, far, device), config, host_clip=(near, far), defer_count=False)

    if near is None and far is None:  # repeated calls of one shape replay a CUDA graph (``_replay``)
        return _replay.render(means, quats, scales, opacities, colors_or_sh, camera, sh_degree, bg, config, eager)
    return eager()


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
    cam_rec = _camera_record(camera, clip, dtype, config.filter_sigma)
    with _bridge.torch_stream(wdev, device):
        bins = _bin(means, quats, scales, opacities, cam_rec, tables, camera, config, wdev, defer_count=defer_count)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, scales, opacities,
                                                                           colors_or_sh))
    means2d = bins.means2d.clone().requires_grad_(needs_grad)
    rgb, alpha, depth, median, normal, dist, vis = _apply_op(bins, rays, cam_rec, bg, means, quats, scales, opacities,
                                                             colors_or_sh, means2d, sh_degree, camera, config, wdev)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                        visibility=vis, radii=bins.radii, means2d=means2d, clip=clip, overflow=bins.overflow,
                        _host_clip=host_clip, _pairs=bins.exact)
