# SPDX-License-Identifier: Apache-2.0
"""What the stages of a fit share: their names, the renderer every stage renders through, its depth maps.

:class:`Stage` names the stages (its values are stored in history records and checkpoints);
:class:`Renderer` renders surfels with the fit's background and rasterizer settings;
:func:`render_depths` gives the depth and colour maps the TSDF stages fuse. The discrete stages themselves
are :func:`~._reinit.tsdf_reinit` (the TSDF re-initialisation) and :func:`~._final_mesh.final_mesh`
(the mesh the fit returns).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Sequence

import numpy as np
import torch

from .._profile import section
from ..scene import NORMALIZATION_MARGIN
from .scene_kind import SceneKind, SceneLayout
from .surfels import Surfels
from .tsdf import FusionBounds

__all__ = ["Stage", "ROI_EXTENT", "TRUNCATION_VOXELS", "ALPHA_THRESHOLD", "Record", "Renderer", "render_depths",
           "roi_bounds"]

ROI_EXTENT = 1.0 - 2 * NORMALIZATION_MARGIN
"""Side of the region of interest in the internal frame: :meth:`wtopo.Scene.normalization` maps it
into ``[m, 1 - m]^3`` (``m = wtopo.scene.NORMALIZATION_MARGIN`` on every side of the unit cube). Distances given
relative to the scene extent are multiplied by this."""
TRUNCATION_VOXELS = 4.0  # TSDF truncation distance in voxels: a few voxels either side of the fused surface
ALPHA_THRESHOLD = 0.5  # pixels rendered less opaque than this are not fused (the median depth exists from 0.5 on)
_ROI_FUSION_MARGIN = 0.05  # scenes fuse the region of interest grown by this fraction of its side (the
# surface at its border is not cut by the fusion's own boundary; the crop to the region comes after)

Record = Callable[..., None]
"""``record(event, **fields)`` appends an event tagged with the current iteration."""


class Stage(str, enum.Enum):
    """A stage of the fit; the value is what history records and checkpoints store."""

    WARMUP = "warmup"
    """Photometric fit with density control, no mesh loss."""
    TSDF = "tsdf"
    """Re-initialisation of the surfels from a TSDF fusion of their rendered depth."""
    COEVOLUTION = "coevolution"
    """Fit with the differentiable proxy mesh and mesh guidance."""
    POLISH = "polish"
    """After the co-evolution: photometric fit only (no mesh terms, guidance or density control)."""
    FINAL = "final"
    """The returned mesh, fused from the surfels last."""


class Renderer:
    """Renders surfels with the fit's background and rasterizer settings.

    Args:
        background: background colour, shape [3], float32, on the fit's device.
        config: :class:`wtopo.rasterize.RasterConfig` of the fit.
    """

    def __init__(self, background: torch.Tensor, config, *, graphs: bool = False):
        from ..rasterize._config import _validate_config
        from .raster_graph import RasterGraphs

        self.background = background
        self.config = _validate_config(config)  # once: the per-call path does not check it again
        self.graphs = RasterGraphs(background, self.config) if graphs else None

    def __call__(self, surfels: Surfels, camera, *, defer_count: bool = False):
        """:func:`wtopo.rasterize.rasterize_surfels` of ``surfels`` seen by ``camera`` (differentiable).

        The fit's tensors are its own and checked by its guards, so the op's argument checks (host
        synchronisations on CUDA) are skipped. ``defer_count``: size the binning from earlier
        calls without reading this call's count; the caller checks ``overflow`` of the output and
        renders again (without it) when set. With ``graphs`` (the fit on CUDA, not profiled) such a
        render is a replay of a CUDA graph when it can be (:mod:`wtopo.fitting.raster_graph`).
        """
        from ..rasterize import _rasterize_trusted

        s = surfels
        if defer_count and self.graphs is not None:  # a replay where the graphs can (on CUDA), else None
            out = self.graphs(s, camera)
            if out is not None:
                return out
        # on CPU reading the count costs nothing and sorting only the real pairs is faster
        defer = defer_count and s.means.is_cuda
        return _rasterize_trusted(s.means, s.quats, s.scales, s.opacities, s.sh, camera, sh_degree=s.sh_degree,
                                  background=self.background, config=self.config, defer_count=defer)


def render_depths(render: Renderer, surfels: Surfels, cameras: Sequence) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Median depth maps [H, W] and colours [H, W, 3] per camera, as NumPy; depth is zero where the
    rendered opacity is below :data:`ALPHA_THRESHOLD`."""
    depths, colors = [], []
    with torch.no_grad(), section("render_depths"):
        for cam in cameras:
            out = render(surfels, cam)
            d = torch.where(out.alpha >= ALPHA_THRESHOLD, out.median_depth, torch.zeros_like(out.median_depth))
            depths.append(d.detach().cpu().numpy())
            colors.append(out.rgb.detach().clamp(0, 1).cpu().numpy())
    return depths, colors


def is_scene(layout: SceneLayout | None) -> bool:
    return layout is not None and layout.kind is SceneKind.SCENE


def roi_bounds(layout: SceneLayout, resolution: int, truncation_voxels: float) -> FusionBounds:
    """Fusion bounds of a scene: the region of interest grown by ``_ROI_FUSION_MARGIN``, ``resolution``
    voxels along its longest side."""
    side = float(np.max(layout.roi_upper - layout.roi_lower))
    lo = layout.roi_lower - _ROI_FUSION_MARGIN * side
    hi = layout.roi_upper + _ROI_FUSION_MARGIN * side
    voxel = float(np.max(hi - lo)) / int(resolution)
    return FusionBounds(lo, hi, voxel, truncation_voxels * voxel)
