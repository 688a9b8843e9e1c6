# SPDX-License-Identifier: Apache-2.0
"""Configuration of :func:`wtopo.fit`: a keyword-only dataclass of nested stage configs.

Every length is in the internal frame (the scene normalised into the unit cube, see
:meth:`wtopo.Scene.normalization`) or relative to the scene extent, so one configuration works
for a scene in millimetres and one in kilometres. Fields set to ``None`` are decided by the stage
plan (:mod:`wtopo.fitting.plan`) from the scene; setting them overrides the plan.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
from dataclasses import dataclass, field

__all__ = [
    "FitConfig",
    "InitConfig",
    "OptimConfig",
    "WarmupConfig",
    "TSDFConfig",
    "CoevolutionConfig",
    "FinalConfig",
    "DensifyConfig",
    "LossConfig",
    "MeshConfig",
    "RuntimeConfig",
    "NormalFlip",
    "DepthLoss",
    "config_hash",
]


class NormalFlip(str, enum.Enum):
    """How the sign of each surfel normal fed to the Poisson solve is chosen."""

    MESH = "mesh"
    """Mesh normal where the nearest proxy face is close and agrees, view directions otherwise."""
    VIEW = "view"
    """Only the accumulated directions towards the cameras that saw the surfel."""
    RANDOM = "random"
    """A random sign per surfel (ablation: shows what the alignment buys)."""


class DepthLoss(str, enum.Enum):
    """Form of the mesh-depth agreement term."""

    LOG_RATIO = "log_ratio"
    """``|log D_surfel - log D_mesh|`` (the method description)."""
    LOG1P_ABS = "log1p_abs"
    """``log1p(|D_mesh - D_surfel| / extent)`` (the public TopoSurfel code)."""


@dataclass(kw_only=True)
class InitConfig:
    """Stage 1: initial surfels."""

    source: str = "auto"
    """``"points"`` (scene points), ``"cameras"`` (random points in the cameras' common volume) or
    ``"auto"`` (points when the scene has them)."""
    num_points: int = 5000
    """Surfels drawn in the common volume when the scene has no points."""
    background_points: int | None = None
    """Background surfels on shells beyond the cameras (scenes without masks,
    :mod:`wtopo.fitting.background`); ``None``: the plan's (as many as ``num_points`` for a scene,
    0 for a masked object)."""
    opacity: float = 0.3
    """Initial opacity in (0, 1)."""
    scale_neighbours: int = 3
    """Initial scale = mean distance to this many nearest neighbours."""


@dataclass(kw_only=True)
class OptimConfig:
    """Adam learning rates per parameter group (internal frame, unit cube).

    Higher than 3DGS's for colour, scale and rotation: the default schedule is hundreds of
    iterations on a CPU, not 30k.
    """

    means: float = 1.6e-3
    """Means, in unit-cube lengths per step; decays to ``means_final``."""
    means_final: float = 1.6e-5
    """Means learning rate at the last iteration (exponential decay)."""
    quats: float = 3e-3
    """Rotations (unnormalised quaternions)."""
    scales: float = 1e-2
    """Log-scales."""
    opacities: float = 5e-2
    """Opacity logits."""
    sh_dc: float = 1e-2
    """SH degree-0 colour (4x the 3DGS rate: the fit runs hundreds, not 30k, iterations)."""
    sh_rest: float = 5e-4
    """Higher SH bands (1/20 of the DC rate, as 3DGS)."""


@dataclass(kw_only=True)
class WarmupConfig:
    """Stage 2: photometric warm-up without mesh losses."""

    iterations: int | None = None
    """Iterations (one view each); ``None``: the plan's budget for the device (CPU 400, CUDA 3000)."""


@dataclass(kw_only=True)
class TSDFConfig:
    """Stage 3 (and the final mesh): TSDF fusion of rendered surfel depth with Open3D.

    Bounds and truncation are derived from the cameras and the current surfels, never given.
    """

    enabled: bool = True
    """Re-initialise the surfels from the fused mesh between warm-up and co-evolution."""
    resolution: int = 128
    """Voxels along the longest side of the automatic bounds."""
    truncation_voxels: float = 4.0
    """Truncation distance in voxels."""
    depth: str = "median"
    """Which rendered depth to fuse: ``"median"`` or ``"expected"``."""
    alpha_threshold: float = 0.5
    """Pixels whose rendered opacity is below this are not fused."""
    max_views: int = 64
    """At most this many views are fused (evenly spaced)."""
    hybrid_distance: float = 0.02
    """Hybrid rule: surfels farther than this (fraction of the scene extent) from the TSDF mesh keep
    their warm-up parameters."""
    max_faces: int = 8000
    """The re-initialisation mesh is decimated to at most this many faces (one surfel each)."""


@dataclass(kw_only=True)
class CoevolutionConfig:
    """Stage 4: surfels and proxy mesh co-evolve; mesh losses every ``mesh_every`` iterations."""

    iterations: int | None = None
    """Iterations; ``None``: the plan's budget for the device (CPU 200, CUDA 1000)."""
    mesh_every: int = 1
    """Rebuild the proxy mesh and apply the mesh losses every this many iterations (1 = always)."""
    correspondence_every: int = 100
    """Refresh nearest-face correspondences (normal signs, geometry-aware density) this often."""
    enabled: bool = True
    """``False`` drops the mesh loop (ablation): the iterations run photometric losses only."""


@dataclass(kw_only=True)
class FinalConfig:
    """Stage 5: the returned mesh."""

    method: str = "tsdf"
    """``"tsdf"``: TSDF fusion of the rendered surfel depth of every training view (automatic
    bounds), re-meshed by Poisson if not closed; ``"proxy"``: the Poisson proxy mesh of the final
    surfels rebuilt at ``poisson_resolution`` (closed by construction). The fused depth is what the
    views see, the proxy is built from every surfel centre, hidden ones included: on the bunny
    the TSDF mesh is the more accurate (0.30 % against 0.42 % of the diagonal, ``benchmarks/fit.md``)."""
    resolution: int | None = None
    """TSDF voxels along the longest side of the fusion bounds; ``None``: the plan's, from the pixel
    footprint at the region of interest (one voxel per pixel footprint, capped per device)."""
    poisson_resolution: int = 128
    """Poisson grid nodes per side for ``method="proxy"``."""
    largest_component: bool = False
    """Keep only the largest connected component. Off by default: components are kept or dropped by
    how well the views support them (size and the number of views that see them,
    :mod:`wtopo.fitting.mesh_policy`), never by rank, so a second object survives."""
    watertight: bool = True
    """Objects: if the TSDF mesh is not closed, re-mesh it by Poisson (closed by construction).
    Scenes (no masks) are never closed: the mesh stays open where nothing was observed."""


@dataclass(kw_only=True)
class DensifyConfig:
    """Density control: 3DGS clone/split plus geometry-aware prune and spawn."""

    enabled: bool | None = None
    """Screen-space clone/split; ``None`` lets the plan decide."""
    start: int = 100
    """First iteration of the warm-up with density control."""
    interval: int = 100
    """Iterations between density-control steps."""
    stop_fraction: float = 0.8
    """Clone/split stops after this fraction of the warm-up."""
    grad_threshold: float = 5e-4
    """Mean screen-space gradient norm (NDC units) above which a surfel is cloned or split."""
    max_growth: float = 0.5
    """One clone/split step adds at most this fraction of the current count (largest gradients first)."""
    percent_dense: float = 0.01
    """Surfels larger than this fraction of the extent are split, smaller ones cloned."""
    prune_opacity: float = 0.05
    """Surfels with opacity below this are pruned."""
    opacity_reset_interval: int = 300
    """Warm-up iterations between opacity resets (0 disables). A reset with fewer than 100 warm-up
    iterations left after it is skipped (the surfels would reach the TSDF re-initialisation still
    transparent)."""
    opacity_reset_value: float = 0.1
    """Opacities are clamped to at most this at a reset."""
    geometry_prune: bool = True
    """Prune surfels far from the proxy mesh AND of low opacity (co-evolution)."""
    geometry_prune_distance: float = 0.02
    """"Far" for the geometry-aware prune, fraction of the scene extent."""
    geometry_prune_opacity: float = 0.3
    """"Low opacity" for the geometry-aware prune."""
    geometry_densify: bool = True
    """Proxy faces that are no surfel's nearest spawn a surfel (co-evolution)."""
    geometry_densify_max: int = 2000
    """At most this many surfels spawned per geometry-aware step."""


@dataclass(kw_only=True)
class LossConfig:
    """Loss weights."""

    dssim: float = 0.2
    """Weight of D-SSIM in the photometric term ``(1 - w) L1 + w (1 - SSIM)``."""
    mask: float | None = None
    """Alpha-vs-mask binary cross-entropy weight; ``None``: plan (0.2 when the scene has masks)."""
    normal: float = 0.05
    """Rendered normal vs depth-derived normal."""
    normal_start: int = 200
    """Warm-up iteration from which the normal term is on (2DGS starts it late)."""
    distortion: float = 100.0
    """Depth distortion."""
    distortion_start: int = 200
    """Warm-up iteration from which the distortion term is on."""
    scale: float = 0.01
    """Scale regulariser (anisotropy penalty for 2-scale surfels, shortest-axis for 3)."""
    max_anisotropy: float = 10.0
    """Ratio of the two surfel scales above which the scale regulariser acts."""
    mesh_depth: float = 0.5
    """Mesh-depth agreement (co-evolution)."""
    mesh_normal: float = 0.05
    """Mesh-normal agreement (co-evolution)."""
    depth_form: DepthLoss = DepthLoss.LOG_RATIO
    """Form of the mesh-depth term."""
    mesh_depth_source: str = "median"
    """Surfel depth compared with the mesh depth: ``"median"`` (where the transmittance crosses 0.5:
    the visible surface) or ``"expected"`` (alpha-weighted mean over the ray, which averages in
    semi-transparent layers behind the surface and drags the proxy inwards: bunny Chamfer 0.281 %
    against 0.262 % with the median, ``benchmarks/fit.md``)."""
    silhouette_band: int = 0
    """With masks: pixels within this many pixels of the mask boundary are left out of the
    photometric and mask terms (0 keeps them). A mask and an image rendered one ray per pixel say
    nothing sub-pixel about where the boundary lies, while splats pay for every fraction of a pixel
    of halo there. On the bunny (3 seeds, ``benchmarks/fit.md``) a 2-pixel band lowers Chamfer a
    little (0.262-0.274 % against 0.272-0.277 %) but costs F-score (0.88 against 0.95) and 1.8 dB
    of PSNR, so it is off by default."""


@dataclass(kw_only=True)
class MeshConfig:
    """The differentiable proxy mesh (oriented points -> Poisson -> marching cubes)."""

    resolution: int | None = None
    """Poisson grid resolution (nodes per side); ``None``: the plan's (CPU 64; CUDA from the pixel
    footprint, 128-256)."""
    sigma: float = 1.0
    """Spectral smoothing of the Poisson solve, in grid cells (0 = none)."""
    padding: float = 0.1
    """Poisson domain padding, fraction of the unit cube."""
    samples_per_surfel: int = 5
    """Oriented points per surfel: 1 (centre) or 5 (centre + 4 tangent offsets)."""
    offset: float = 0.5
    """Tangent offset of the extra samples, in surfel sigmas."""
    offset_weight: float = 0.5
    """Weight of the extra samples relative to the centre."""
    normal_flip: NormalFlip = NormalFlip.MESH
    """Normal sign rule (mesh | view | random)."""
    flip_distance: float = 0.02
    """A surfel takes the mesh normal's sign when the nearest face is closer than this (extent fraction)."""
    opacity_threshold: float = 0.0
    """Surfels below this opacity do not contribute oriented points."""
    poisson_box: str = "unit"
    """``"unit"``: Poisson on the normalised unit cube; ``"initial_mesh"``: on the TSDF mesh's box + 10 %
    (public TopoSurfel code)."""
    surface_prior: float = 0.0
    """Weight of a surface prior splatted from the TSDF mesh into the Poisson input (public code: on)."""


@dataclass(kw_only=True)
class RuntimeConfig:
    """Device, reproducibility, checkpoints, progress."""

    device: str = "auto"
    """``"auto"`` (CUDA when available), ``"cpu"`` or ``"cuda:N"``."""
    seed: int = 0
    """Seed of torch, NumPy and every random choice of the fit."""
    max_surfels: int | None = None
    """Hard cap on the surfel count; ``None``: the plan's (CPU 40,000, CUDA 400,000)."""
    checkpoint_every: int = 200
    """Iterations between checkpoints (0: none except at stage ends and on interruption)."""
    checkpoint_seconds: float = 120.0
    """Also checkpoint when this much wall-clock time passed since the last one."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (>= 2)."""
    eval_every: int = 200
    """Iterations between history records (losses, and metrics when ground truth exists)."""
    eval_views: int = 4
    """Held-out views for PSNR (taken from the scene's views, not trained on)."""
    eval_metrics: bool = True
    """Compute Chamfer / F-score / PSNR at evaluations when the scene has a ground-truth mesh."""
    usd_every: int = 100
    """Write a timeline frame every this many iterations to ``out_dir/timeline.usdc`` (0: none)."""
    max_consecutive_failures: int = 20
    """Abort (with a checkpoint) after this many non-finite steps in a row."""
    progress: bool = True
    """tqdm progress bars (also ``fit(progress=...)``)."""
    image_scale: float | None = None
    """Train on images resized by this factor (1.0: full resolution); ``None``: the plan decides
    from the image size and the device."""
    stop_at: int | None = None
    """Stop as if interrupted once this global iteration is reached (time-boxed runs, tests); the
    run resumes from its checkpoint with ``stop_at`` cleared."""


@dataclass(kw_only=True)
class FitConfig:
    """Everything :func:`wtopo.fit` takes, grouped by stage.

    ``FitConfig.toposurfel_public()`` returns the settings of the public TopoSurfel code where wtopo
    can reproduce them (see ``ANCHORS.md``).

    Limitations:
        Two differences of the public code are not reproducible here: flattened 3D Gaussians
        (wtopo renders 2D surfels) and dual marching cubes (wtopo uses plain marching cubes).
    """

    init: InitConfig = field(default_factory=InitConfig)
    """Stage 1."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Learning rates."""
    warmup: WarmupConfig = field(default_factory=WarmupConfig)
    """Stage 2."""
    tsdf: TSDFConfig = field(default_factory=TSDFConfig)
    """Stage 3."""
    coevolution: CoevolutionConfig = field(default_factory=CoevolutionConfig)
    """Stage 4."""
    final: FinalConfig = field(default_factory=FinalConfig)
    """Stage 5."""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """Density control."""
    losses: LossConfig = field(default_factory=LossConfig)
    """Loss weights."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Proxy mesh."""
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    """Runtime."""
    kind: str | None = None
    """``"object"`` (closed mesh, nothing behind it kept) or ``"scene"`` (background kept at
    distance, open mesh of the region of interest); ``None``: the plan's (object when the scene has
    masks). See :mod:`wtopo.fitting.scene_kind`."""
    sh_degree: int | None = None
    """SH degree of the colours (0..3); ``None``: plan (0 for an untextured scene)."""
    background: tuple[float, float, float] | None = None
    """Background colour behind the surfels; ``None``: the scene's, else plan."""
    filter_sigma: float = 0.35
    """Screen-space low-pass of the surfel renderer [pixels] (:class:`wtopo.RasterConfig`; 2DGS uses
    0.71). Half the 2DGS width: a sub-pixel surfel seen edge-on at the silhouette then haloes half
    as far, the fit shrinks the surface less to cancel the halo, and rendered depth stops leaning
    towards the nearest centre (bunny, other settings as before: Chamfer 0.74 % -> 0.44 %; with
    today's defaults see ``benchmarks/fit.md``)."""

    @staticmethod
    def toposurfel_public() -> FitConfig:
        """Settings matching the public TopoSurfel code (ANCHORS.md) as far as wtopo supports them:
        a long separate initialisation, 1 point per surfel, Poisson without spectral smoothing on the
        initial mesh's box + 10 % at a fine grid with a surface prior, log1p depth loss weight 0.05,
        mesh-normal weight 0, far-from-mesh prune disabled."""
        cfg = FitConfig()
        cfg.warmup.iterations = 15000
        cfg.mesh.samples_per_surfel = 1
        cfg.mesh.sigma = 0.0
        cfg.mesh.resolution = 360
        cfg.mesh.poisson_box = "initial_mesh"
        cfg.mesh.surface_prior = 1.0
        cfg.losses.depth_form = DepthLoss.LOG1P_ABS
        cfg.losses.mesh_depth = 0.05
        cfg.losses.mesh_normal = 0.0
        cfg.densify.geometry_prune = False
        return cfg

    def to_dict(self) -> dict:
        """Plain nested dict (enums as their values), JSON-serialisable."""
        return json.loads(json.dumps(dataclasses.asdict(self), default=_json_default))

    @staticmethod
    def from_dict(d: dict) -> FitConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        cfg = FitConfig()
        for key, value in d.items():
            if not hasattr(cfg, key):
                raise ValueError(f"FitConfig has no field {key!r}")
            cur = getattr(cfg, key)
            if dataclasses.is_dataclass(cur):
                for k, v in value.items():
                    if not hasattr(cur, k):
                        raise ValueError(f"FitConfig.{key} has no field {k!r}")
                    old = getattr(cur, k)
                    setattr(cur, k, type(old)(v) if isinstance(old, enum.Enum) else v)
            else:
                setattr(cfg, key, tuple(value) if isinstance(value, list) else value)
        return cfg


def _json_default(o):
    if isinstance(o, enum.Enum):
        return o.value
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def config_hash(cfg: FitConfig, *, ignore=("runtime",)) -> str:
    """SHA-256 (16 hex digits) of the configuration, without the groups in ``ignore``.

    Runtime settings (progress bars, checkpoint cadence) do not change the result, so a run may be
    resumed with different ones; the seed is always hashed.
    """
    d = cfg.to_dict()
    seed = d["runtime"]["seed"]
    for k in ignore:
        d.pop(k, None)
    d["seed"] = seed  # the seed changes the result even though it lives in ``runtime``
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
