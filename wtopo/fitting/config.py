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
import math
from dataclasses import dataclass, field

from ..rasterize import FILTER_SIGMA_RANGE
from .config_fields import REMOVED, Leaf, RemovedFieldError, leaves, set_field
from .config_kinds import (
    _GRID_MIN,
    COUNT,
    FRACTION,
    POSITIVE,
    RATE,
    DepthLoss,
    InitSource,
    NormalFlip,
    PoissonBox,
    Preset,
    Range,
    _f,
)
from .config_loop import LossConfig, MeshConfig
from .scene_kind import SceneKind

__all__ = [
    "FitConfig",
    "InitConfig",
    "OptimConfig",
    "WarmupConfig",
    "TSDFConfig",
    "CoevolutionConfig",
    "PolishConfig",
    "FinalConfig",
    "DensifyConfig",
    "LossConfig",
    "MeshConfig",
    "RuntimeConfig",
    "NormalFlip",
    "InitSource",
    "PoissonBox",
    "Preset",
    "DepthLoss",
    "config_hash",
    "stage_iteration",
    "Range",
    "Leaf",
    "leaves",
    "set_field",
    "RemovedFieldError",
    "REMOVED",
]

_TSDF_MAX = 2048  # Open3D's TSDF volume is sparse, the Warp one fused in slabs: 2048 per side stays in memory
_SEED_MAX = 2**32 - 1  # NumPy's default_rng and torch.manual_seed (times 1_000_003) both accept this range
_SH_MAX = 3  # the renderer evaluates SH bands 0..3



@dataclass(kw_only=True)
class InitConfig:
    """Stage 1: initial surfels."""

    source: InitSource = InitSource.AUTO
    """Where the initial surfels come from."""
    num_points: int = _f(5000, POSITIVE)
    """Surfels drawn in the common volume, or kept of the stereo points, when the scene has no points."""
    background_points: int | None = _f(None, COUNT)
    """Background surfels on shells beyond the cameras; ``None``: the plan's (``num_points`` for a scene,
    0 for an object). Left to the plan, a scene seeds none when most of the pixels its stereo left unexplained are
    untextured (the printed plan and ``plan.json`` then say so); a number set here is seeded whatever the texture."""


@dataclass(kw_only=True)
class OptimConfig:
    """Adam learning rates per parameter group (internal frame: the scene in the unit cube)."""

    means: float = _f(1.6e-3, RATE)
    """Means [unit-cube lengths per step]; decays exponentially to ``means_final``."""
    means_final: float = _f(1.6e-5, RATE)
    """Means rate at the end of the decay [unit-cube lengths per step]."""
    means_decay_iterations: int | None = _f(None, POSITIVE)
    """Iterations over which the means' rate decays to ``means_final``, then stays there; ``None``: the
    plan's (CPU: the whole fit; CUDA: the warm-up and half the co-evolution)."""
    means_restart: float | None = _f(None, FRACTION, was_bool=True)
    """Restart the means' rate at the co-evolution at this fraction of ``means``, decaying to ``means_final``
    at the last iteration (0: no restart); ``None``: the plan's (CPU 0, CUDA 0.0625)."""
    quats: float = _f(3e-3, RATE)
    """Rotations (unnormalised quaternions) [per step]."""
    scales: float = _f(1e-2, RATE)
    """Log-scales [per step]."""
    opacities: float = _f(5e-2, RATE)
    """Opacity logits [per step]."""
    sh_dc: float = _f(1e-2, RATE)
    """SH degree-0 colour [per step]; the higher bands take 1/20 of the 3DGS-like default."""


@dataclass(kw_only=True)
class WarmupConfig:
    """Stage 2: photometric warm-up without mesh losses."""

    iterations: int | None = _f(None, COUNT)
    """Iterations (one view each); ``None``: the plan's budget (:func:`wtopo.fitting.plan.iteration_budget`)."""


@dataclass(kw_only=True)
class TSDFConfig:
    """Stage 3: TSDF fusion of rendered surfel depth, re-initialising the surfels (bounds are automatic)."""

    enabled: bool | None = None
    """Re-initialise the surfels from the fused mesh between warm-up and co-evolution; ``None``: the plan's (off
    for a scene whose proxy-mesh loop is off, where nothing would use the re-initialised surfels; on otherwise)."""
    resolution: int | None = _f(None, Range(_GRID_MIN, _TSDF_MAX))
    """Voxels along the longest side of the automatic bounds; ``None``: the plan's (the final mesh's voxel of
    0.8 pixel footprints, at most 128 voxels)."""
    max_faces: int | None = _f(None, POSITIVE)
    """The fused mesh is decimated to at most this many faces (one surfel each); ``None``: the plan's,
    from the pixel footprint and the views per point, capped per device."""


@dataclass(kw_only=True)
class CoevolutionConfig:
    """Stage 4: surfels and proxy mesh co-evolve; the proxy is rebuilt and the mesh losses applied every iteration
    (every second one on the CPU at the ``fast`` and ``balanced`` presets)."""

    iterations: int | None = _f(None, COUNT)
    """Iterations; ``None``: the plan's budget (:func:`wtopo.fitting.plan.iteration_budget`)."""
    enabled: bool | None = None
    """Whether the proxy-mesh loop runs (``False``: photometric iterations only); ``None``: the plan's (on
    for objects, off for scenes)."""


@dataclass(kw_only=True)
class PolishConfig:
    """Stage 5, after the co-evolution: the surfels train on the photographs alone (no mesh terms, no density control),
    releasing them from the proxy's pull; the final mesh is fused from them afterwards (``surfels.ply``, the
    held-out renders and the mesh all come from the polished surfels)."""

    iterations: int | None = _f(None, COUNT)
    """Iterations; ``None``: the plan's (after a proxy-mesh loop half the co-evolution's, none at ``fast``; none
    without a loop)."""


@dataclass(kw_only=True)
class FinalConfig:
    """Stage 6: the returned mesh, TSDF fusion of the rendered surfel depth of every training view."""

    resolution: int | None = _f(None, Range(_GRID_MIN, _TSDF_MAX))
    """TSDF voxels along the longest side of the fusion bounds; ``None``: the plan's (one voxel per 0.8
    pixel footprints at the region of interest, twice as fine where the co-evolution finds thin parts,
    within the preset's range)."""
    watertight: bool = True
    """Objects: Poisson re-meshes a fused mesh that is not closed. Scenes are never closed."""
    outline: bool = True
    """Masked objects: the mesh moves along its normals until its ray-cast silhouettes cover the training masks
    along its smooth limbs (:func:`wtopo.geometry.outline.outline_offset`, the median over the views, at most one
    pixel footprint; where the silhouettes fall short, the outline its sharp edges draw is not counted, and a mesh
    whose outline is all edges stays;
    an object too thin for the mesh terms only inward)."""


@dataclass(kw_only=True)
class DensifyConfig:
    """Density control: 3DGS clone/split plus geometry-aware prune and spawn."""

    enabled: bool | None = None
    """Screen-space clone/split in the warm-up; ``None``: the plan's."""
    interval: int | None = _f(None, POSITIVE)
    """Iterations between density-control steps; ``None``: the plan's (an eighth of the warm-up, 10-100)."""
    opacity_reset_fraction: float = _f(0.75, FRACTION)
    """Opacity resets every this fraction of the warm-up (0: none)."""
    geometry_prune: bool = True
    """Co-evolution: prune surfels far from the proxy mesh and of low opacity."""
    geometry_densify: bool = True
    """Co-evolution: proxy faces no surfel is nearest to spawn a surfel."""


@dataclass(kw_only=True)
class RuntimeConfig:
    """Device, reproducibility, checkpoints, progress."""

    device: str = field(default="auto", metadata={"pattern": r"auto|cpu|cuda(:\d+)?"})
    """``"auto"`` (CUDA when available), ``"cpu"`` or ``"cuda:N"``."""
    seed: int = _f(0, Range(0, _SEED_MAX))
    """Seed of torch, NumPy and every random choice of the fit."""
    max_surfels: int | None = _f(None, POSITIVE)
    """Hard cap on the surfel count; ``None``: the plan's (CPU 40,000, CUDA 400,000)."""
    checkpoint_every: int = _f(1000, COUNT)
    """Iterations between checkpoints (0: only every 2 minutes, when the iterations end or are interrupted)."""
    eval_every: int = _f(200, COUNT)
    """Iterations between history records (losses, and metrics when ground truth exists)."""
    eval_views: int = _f(4, COUNT)
    """Views held out for PSNR when the scene has no test split (not trained on)."""
    eval_metrics: bool = True
    """Compute Chamfer / F-score / PSNR at evaluations when the scene has a ground-truth mesh."""
    usd_every: int = _f(100, COUNT)
    """Iterations between frames of ``out_dir/timeline.usdc`` (0: none)."""
    progress: bool = True
    """tqdm progress bars and the printed plan (also ``fit(progress=...)``)."""
    profile: bool = False
    """Print and report the time per stage; on CUDA every timed section then synchronises the device."""
    image_scale: float | None = _f(None, Range(0.0, 1.0, lo_open=True))
    """Train on images resized by this factor; ``None``: the plan's (longest side capped per preset and device)."""
    stop_at: int | None = _f(None, COUNT)
    """Stop as if interrupted at this global iteration (time-boxed runs); resume with it cleared."""
    start_from: str | None = field(default=None, metadata={"pattern": r".+"})
    """A run directory whose newest warm-up checkpoint this fit starts from (paired ablations): the two
    configurations may differ only in what acts after the warm-up
    (:data:`~wtopo.fitting.checkpointing.AFTER_WARMUP`)."""


@dataclass(kw_only=True)
class FitConfig:
    """Everything :func:`wtopo.fit` takes, grouped by stage.

    ``FitConfig.toposurfel_public()`` returns the settings of the public TopoSurfel code where wtopo
    can reproduce them (see ``design/toposurfel.md``).

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
    """Stage 6 (after the polish)."""
    polish: PolishConfig = field(default_factory=PolishConfig)
    """Stage 5."""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """Density control."""
    losses: LossConfig = field(default_factory=LossConfig)
    """Loss weights."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Proxy mesh."""
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    """Runtime."""
    preset: Preset = Preset.BALANCED
    """Budgets the plan starts from: ``fast``, ``balanced`` or ``best`` (:mod:`wtopo.fitting.presets`); a
    field set here still wins over its preset."""
    kind: SceneKind | None = None
    """``OBJECT`` (closed mesh) or ``SCENE`` (background kept, open mesh of the region of interest);
    ``None``: the plan's (object when the scene has masks)."""
    sh_degree: int | None = _f(None, Range(0, _SH_MAX))
    """SH degree of the colours (0..3); ``None``: the plan's (0 for an untextured or diffuse scene or one of under
    20 training views, else 3)."""
    background: tuple[float, float, float] | None = _f(None, FRACTION)
    """RGB background colour behind the surfels, in [0, 1]; ``None``: the scene's, else black."""
    filter_sigma: float | None = _f(None, Range(*FILTER_SIGMA_RANGE))
    """Screen-space low-pass of the surfel renderer [pixels] (:class:`wtopo.ops.RasterConfig`); ``None``: the plan's
    (0.25 on CUDA, 0.35 on the CPU; 2DGS's is 0.71). Render fitted surfels with the plan's value
    (``FitResult.plan.filter_sigma``)."""

    @staticmethod
    def toposurfel_public() -> FitConfig:
        """Settings matching the public TopoSurfel code (design/toposurfel.md) as far as wtopo supports them:
        a long separate initialisation, 1 point per surfel, Poisson without spectral smoothing on the
        initial mesh's box + 10 % at a fine grid with a surface prior, log1p depth loss weight 0.05 (not
        debiased), mesh-normal weight 0, far-from-mesh prune disabled, no polish (that code has none)."""
        cfg = FitConfig()
        cfg.polish.iterations = 0
        cfg.warmup.iterations = 15000
        cfg.mesh.samples_per_surfel = 1
        cfg.mesh.sigma = 0.0
        cfg.mesh.resolution = 360
        cfg.mesh.poisson_box = PoissonBox.INITIAL_MESH
        cfg.mesh.surface_prior = 1.0
        cfg.losses.depth_form = DepthLoss.LOG1P_ABS
        cfg.losses.mesh_depth = 0.05
        cfg.losses.mesh_depth_debias = False
        cfg.losses.mesh_normal = 0.0
        cfg.densify.geometry_prune = False
        return cfg

    def to_dict(self) -> dict:
        """Plain nested dict (enums as their values), JSON-serialisable."""
        return json.loads(json.dumps(dataclasses.asdict(self), default=_json_default))

    @staticmethod
    def from_dict(d: dict) -> FitConfig:
        """Inverse of :meth:`to_dict` (a partial dict leaves the other fields at their defaults).

        Raises:
            RemovedFieldError: ``d`` holds fields that earlier versions had and this one removed (a
                ``config.json`` of an older run); the message names every one of them.
            ValueError: an unknown key (named by its dotted path) or an unknown enum string.
        """
        cfg = FitConfig()

        def flat(node: dict, prefix: str):
            for key, value in node.items():
                if isinstance(value, dict):
                    yield from flat(value, f"{prefix}{key}.")
                else:
                    yield f"{prefix}{key}", value

        items = list(flat(d, ""))
        gone = [path for path, _ in items if path in REMOVED]
        if gone:
            raise RemovedFieldError(gone, saved=True)
        for path, value in items:
            set_field(cfg, path, value)
        return cfg


def stage_iteration(fraction: float, iterations: int) -> int:
    """The iteration ``fraction`` of the way through a stage of ``iterations`` (nearest; halves round up).

    Schedules are fractions of their stage so that one configuration keeps its shape at any budget:
    with the CPU warm-up of 800 iterations, a fraction of 0.25 is iteration 200.
    """
    return math.floor(fraction * iterations + 0.5)


def _json_default(o):
    if isinstance(o, enum.Enum):
        return o.value
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


_LATER_GROUPS = {"polish": {"iterations": None}}
"""Groups added after checkpoints were first written, with their default values: a configuration holding them at
these values hashes as it did before them, so a run directory of an earlier version resumes."""


def config_hash(cfg: FitConfig, *, ignore=("runtime",)) -> str:
    """SHA-256 (16 hex digits) of the configuration, without the groups in ``ignore``.

    Runtime settings (progress bars, checkpoint cadence) do not change the result, so a run may be
    resumed with different ones; the seed is always hashed.
    """
    d = cfg.to_dict()
    seed = d["runtime"]["seed"]
    for k in ignore:
        d.pop(k, None)
    for k, default in _LATER_GROUPS.items():  # at their defaults, groups added later leave earlier hashes as they were
        if d.get(k) == default:
            d.pop(k)
    d["seed"] = seed  # the seed changes the result even though it lives in ``runtime``
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
