# SPDX-License-Identifier: Apache-2.0
"""The loss terms and the proxy mesh of :class:`~wtopo.fitting.config.FitConfig` (``losses`` and ``mesh``),
re-exported by :mod:`wtopo.fitting.config`."""

from __future__ import annotations

from dataclasses import dataclass

from .config_kinds import (
    _GRID_MIN,
    _POISSON_MAX,
    FRACTION,
    RATE,
    DepthLoss,
    NormalFlip,
    PoissonBox,
    Range,
    _f,
)

__all__ = ["LossConfig", "MeshConfig"]


@dataclass(kw_only=True)
class LossConfig:
    """Loss weights (dimensionless multipliers of each term)."""

    mask: float | None = _f(None, RATE)
    """Alpha-vs-mask binary cross-entropy weight; ``None``: the plan's (0.2 when the scene has masks, else 0)."""
    normal: float = _f(0.05, RATE)
    """Rendered normal vs depth-derived normal, from mid warm-up on."""
    distortion: float = _f(100.0, RATE)
    """Depth distortion, from mid warm-up on."""
    scale: float = _f(0.01, RATE)
    """Scale regulariser (penalises surfels more anisotropic than 10:1)."""
    mesh_depth: float = _f(3.0, RATE)
    """Surfel-vs-proxy log-depth agreement (co-evolution)."""
    mesh_normal: float = _f(0.05, RATE)
    """Surfel-vs-proxy normal agreement (co-evolution)."""
    mesh_thin_limit: float = _f(0.15, FRACTION)
    """Share of the proxy's pixels seen through parts under ``2 mesh.sigma + 1`` Poisson cells thick above
    which the proxy's grid doubles for the co-evolution, and the mesh terms stay off if still above it
    (:mod:`~wtopo.fitting.thin_parts`); 1: never."""
    depth_form: DepthLoss = DepthLoss.LOG_RATIO
    """Form of the mesh-depth term."""
    mesh_depth_debias: bool = True
    """The mesh-depth term ignores each view's median offset between the surfels' and the proxy's depth
    (the proxy's Poisson smoothing shifts convex objects inwards)."""
    multiview: float | None = _f(None, RATE)
    """Multi-view patch NCC against two neighbouring photographs (:mod:`wtopo.fitting.multiview`), from mid
    warm-up on; ``None``: the plan's (0.15 when the photographs have texture, else 0)."""


@dataclass(kw_only=True)
class MeshConfig:
    """The differentiable proxy mesh (oriented points -> Poisson -> marching cubes)."""

    resolution: int | None = _f(None, Range(_GRID_MIN, _POISSON_MAX))
    """Poisson grid nodes per side; ``None``: the plan's (CPU 64, 48 at ``fast``; CUDA 128-256, 128-192 at
    ``fast``, from the pixel footprint)."""
    sigma: float = _f(1.0, RATE)
    """Spectral smoothing of the Poisson solve [grid cells] (0: none)."""
    samples_per_surfel: int = _f(5, (1, 5))
    """Oriented points per surfel: 1 (centre) or 5 (centre + 4 tangent offsets)."""
    normal_flip: NormalFlip = NormalFlip.MESH
    """How the sign of each oriented point's normal is chosen (``VIEW`` and ``RANDOM`` are ablations)."""
    poisson_box: PoissonBox = PoissonBox.UNIT
    """Domain of the Poisson solve."""
    surface_prior: float = _f(0.0, RATE)
    """Weight of a surface prior splatted from the TSDF mesh into the Poisson input (0: none)."""
    level_sigma: float | None = _f(None, RATE)
    """Zero level of the Poisson indicator: 0, one global level; > 0, a local level under a Gaussian of
    this many grid cells (keeps an open ground on its points); ``None``: the plan's (scenes 2, objects 0)."""
    clip_to_region: bool | None = None
    """Build the proxy from the points near the region of interest and keep only its faces there;
    ``None``: the plan's (scenes yes, objects no)."""
