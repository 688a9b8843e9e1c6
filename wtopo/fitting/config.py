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
from .config_fields import Leaf, leaves, set_field
from .config_kinds import (
    _GRID_MIN,
    _POISSON_MAX,
    COUNT,
    FRACTION,
    OPEN_UNIT,
    POSITIVE,
    RATE,
    Closure,
    DepthLoss,
    FinalMethod,
    InitSource,
    NormalFlip,
    PoissonBox,
    Range,
    RenderedDepth,
    TSDFBackend,
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
    "FinalConfig",
    "DensifyConfig",
    "LossConfig",
    "MeshConfig",
    "RuntimeConfig",
    "NormalFlip",
    "InitSource",
    "RenderedDepth",
    "FinalMethod",
    "PoissonBox",
    "TSDFBackend",
    "DepthLoss",
    "config_hash",
    "stage_iteration",
    "Range",
    "Leaf",
    "leaves",
    "set_field",
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
    """Background surfels on shells beyond the cameras (scenes without masks,
    :mod:`wtopo.fitting.background`); ``None``: the plan's (as many as ``num_points`` for a scene,
    0 for a masked object)."""
    opacity: float = _f(0.3, OPEN_UNIT)
    """Initial opacity in (0, 1)."""


@dataclass(kw_only=True)
class OptimConfig:
    """Adam learning rates per parameter group (internal frame, unit cube).

    Higher than 3DGS's for colour, scale and rotation: the default schedule is hundreds of
    iterations on a CPU, not 30k.
    """

    means: float = _f(1.6e-3, RATE)
    """Means, in unit-cube lengths per step; decays to ``means_final``."""
    means_final: float = _f(1.6e-5, RATE)
    """Means learning rate at the last iteration (exponential decay)."""
    means_decay_iterations: int | None = _f(None, POSITIVE)
    """The single decay reaches ``means_final`` after this many iterations and stays there; ``None`` (the
    default): over all of the fit's iterations. Keeps a schedule's rates when the co-evolution is
    lengthened (1,200: the rates of the CPU budget's former 800 + 400 under 800 + 800)."""
    means_thin_decay: float = _f(0.5, FRACTION)
    """Where the co-evolution's thin-part rule refined the proxy's grid (:mod:`wtopo.fitting.thin_parts`:
    over ``losses.mesh_thin_limit`` of the proxy's pixels look through parts a few cells thick), the
    co-evolution's means follow a single decay that reaches ``means_final`` this fraction of the way
    through the co-evolution (0.5 under 800 + 800: the rates of 800 + 400); the warm-up and fits where
    the rule does not fire keep the fit's own decay. ``0``: the fit's own decay everywhere. Thin parts thin
    out under the longer co-evolution's higher rate (``benchmarks/hard.md``, ``cpu_coevo800``); at 0.5
    (``cpu_thin_decay``) the chairs' loop Chamfer falls 2-6 % (chair_box, chair, ten-view chair) and a
    held-out table's 10-12 %; the rule fires on no other suite scene, the bunny or the sphere rig."""
    means_restart: float | None = _f(None, FRACTION, was_bool=True)
    """Restart the means schedule at the co-evolution: it starts at this fraction of ``means`` (never
    below where the single decay stands there) and decays to ``means_final`` at its last iteration (not
    where the thin-part rule ended the co-evolution's decay sooner, ``means_thin_decay``). ``None``: the
    plan's (:mod:`wtopo.fitting.plan`): 0.0625 on CUDA (1e-4; at 512 px the loop's fits -3.7 % on the hard
    suite's mean, ``benchmarks/hard.md`` ``gpu_restart``), 0 on the CPU. ``0``: one decay over both stages,
    so the co-evolution starts at ~7e-5 on the CPU budget (then 400 + 200) and moves surfels by < 1 pixel;
    ``1``: the public code's full restart. On the CPU, hard
    suite with the current mesh-depth default, 7 objects x 2 seeds (``benchmarks/hard.md``,
    ``cpu_restart``): ``1`` removes the bowl's and the blob's shrink (-16 to -26 %) but swells the
    chair, chair_box and mug (+15 to +45 %), and the loop's own gain falls from 5.0 % to 3.5 %.
    ``0.3`` (``cpu_restart03``): mean Chamfer -5.1 % against 0 (bowl, blob -20 to -25 %) but chair
    +15 / +17 % and chair_box +20 / +24 %; the loop's own gain -6.4 % with chair_box +11 / +13 %: off."""
    means_restart_along_normal: bool = False
    """With ``means_restart``: the restarted rate moves a surfel only along its normal; the in-plane
    part of each step is scaled back to the single decay's rate (:mod:`wtopo.fitting.schedule`).
    Hard suite at ``means_restart=0.3`` (``cpu_restart03``): the same as without it (mean 0.408 against
    0.407 %, chair +17 %), so the thin parts' loss is not in-plane sliding: off."""
    quats: float = _f(3e-3, RATE)
    """Rotations (unnormalised quaternions)."""
    scales: float = _f(1e-2, RATE)
    """Log-scales."""
    opacities: float = _f(5e-2, RATE)
    """Opacity logits."""
    sh_dc: float = _f(1e-2, RATE)
    """SH degree-0 colour (4x the 3DGS rate: the fit runs hundreds, not 30k, iterations)."""
    sh_rest: float = _f(5e-4, RATE)
    """Higher SH bands (1/20 of the DC rate, as 3DGS)."""


@dataclass(kw_only=True)
class WarmupConfig:
    """Stage 2: photometric warm-up without mesh losses."""

    iterations: int | None = _f(None, COUNT)
    """Iterations (one view each); ``None``: the plan's budget for the device (CPU 800, CUDA 3000; a CPU
    budget grows with the pixels to fit, :func:`wtopo.fitting.plan.iteration_budget`)."""


@dataclass(kw_only=True)
class TSDFConfig:
    """Stage 3 (and the final mesh): TSDF fusion of rendered surfel depth (Warp or Open3D).

    Bounds and truncation are derived from the cameras and the current surfels, never given.
    """

    enabled: bool = True
    """Re-initialise the surfels from the fused mesh between warm-up and co-evolution."""
    resolution: int = _f(128, Range(_GRID_MIN, _TSDF_MAX))
    """Voxels along the longest side of the automatic bounds."""
    truncation_voxels: float = _f(4.0, Range(0.0, lo_open=True))
    """Truncation distance in voxels."""
    depth: RenderedDepth = RenderedDepth.MEDIAN
    """Which rendered depth to fuse."""
    alpha_threshold: float = _f(0.5, RATE)
    """Pixels whose rendered opacity is below this are not fused."""
    max_faces: int | None = _f(None, POSITIVE)
    """The re-initialisation mesh is decimated to at most this many faces (one surfel each);
    ``None``: the plan's, from the pixel footprint: 0.25 faces per squared footprint of the region of
    interest's box surface (each surfel starts about a footprint across), between 8,000 and the device's
    cap (CPU 8,000; CUDA a quarter of the surfel cap; ``benchmarks/hard.md``, ``gpu_reinit_rule``)."""
    backend: TSDFBackend = TSDFBackend.AUTO
    """Fusion of the re-initialisation and the final TSDF mesh: ``AUTO`` (the plan's: Warp on CUDA,
    Open3D on the CPU), ``WARP`` or ``OPEN3D``."""


@dataclass(kw_only=True)
class CoevolutionConfig:
    """Stage 4: surfels and proxy mesh co-evolve; the proxy is rebuilt and the mesh losses applied every iteration."""

    iterations: int | None = _f(None, COUNT)
    """Iterations; ``None``: the plan's budget for the device (CPU 800, CUDA 1000; a CPU budget grows
    with the pixels to fit, :func:`wtopo.fitting.plan.iteration_budget`)."""
    correspondence_fraction: float = _f(0.5, FRACTION)
    """Refresh nearest-face correspondences (normal signs, geometry-aware density) every this fraction
    of the co-evolution (:func:`stage_iteration`; at least every iteration), from its first iteration."""
    enabled: bool | None = None
    """Whether the proxy-mesh loop runs; ``False`` drops it (ablation): the iterations run photometric
    losses only. ``None``: the plan decides: on for objects, off for scenes (no masks, background kept),
    whose Poisson proxy closes the open, box-cut surface where no view supports it (on the hard suite's
    chair on a ground, ``benchmarks/hard.md``: proxy 1.9-7.8 % of the diagonal from the truth against
    1.2 % for the surfels, the mesh-depth term pulling correct surfels on 30-50 % of its pixels and
    helping on 0-4 %; with the mesh-guided sign fix the proxy still loses the floor under the mesh
    terms and the final mesh is 0.91 % off against 0.63 % without the loop)."""


@dataclass(kw_only=True)
class FinalConfig:
    """Stage 5: the returned mesh."""

    method: FinalMethod = FinalMethod.TSDF
    """``TSDF``: TSDF fusion of the rendered surfel depth of every training view (automatic
    bounds), re-meshed by Poisson if not closed; ``PROXY``: the Poisson proxy mesh of the final
    surfels rebuilt at ``poisson_resolution`` (closed by construction). The fused depth is what the
    views see, the proxy is built from every surfel centre, hidden ones included: on the bunny
    the TSDF mesh is the more accurate (0.30 % against 0.42 % of the diagonal, ``benchmarks/fit.md``)."""
    resolution: int | None = _f(None, Range(_GRID_MIN, _TSDF_MAX))
    """TSDF voxels along the longest side of the fusion bounds; ``None``: the plan's, from the pixel
    footprint at the region of interest (one voxel per pixel footprint, capped per device)."""
    poisson_resolution: int = _f(128, Range(_GRID_MIN, _POISSON_MAX))
    """Poisson grid nodes per side for ``method=PROXY``."""
    largest_component: bool = False
    """Keep only the largest connected component. Off by default: components are kept or dropped by
    how well the views support them (size and the number of views that see them,
    :mod:`wtopo.fitting.mesh_policy`), never by rank, so a second object survives."""
    watertight: bool = True
    """Objects: close the mesh where the views left it open (``closure``); Poisson re-meshes whatever is
    still not closed. Scenes (no masks) are never closed: the mesh stays open where nothing was observed."""
    closure: Closure = Closure.POISSON
    """How an object's TSDF mesh is closed (``watertight``): ``CARVE`` fuses with the Warp kernel and
    closes along the space the views saw empty, keeping the fused surface; ``POISSON`` re-meshes an
    open TSDF mesh whole. Hard suite (``benchmarks/hard.md``, ``cpu_closure``, the ``cpu_s23`` fits
    re-meshed): carving keeps the mug's seen surface (0.499 -> 0.458 %) but the boxy chair loses
    Poisson's smoothing (0.129 -> 0.137 %) and 10 views carve the sparse mug loosely (1.410 -> 2.047 %):
    mean 0.437 -> 0.524 %, so ``POISSON`` stays the default."""
    silhouette_calibration: bool = False
    """Objects with masks: move the final mesh along its vertex normals until its silhouettes sit on
    the training masks (:func:`wtopo.fitting.silhouette.calibrate_mesh`; at most one pixel footprint).
    The surfels' soft rim covers the masks while the surface fused from their depth lies 0.2-0.5 px
    inside. On the hard suite (``benchmarks/hard.md``) it lowers the mean Chamfer of the 7 objects by
    10-12 % (smooth ones: torus 0.185 -> 0.095 %, blob 0.343 -> 0.155 %, bowl 0.361 -> 0.255 %) but
    thickens the thin, boxy chair (0.129 -> 0.183 %), whose silhouette deficit comes from rounded edges,
    not a shrink; off by default until that is told apart."""


@dataclass(kw_only=True)
class DensifyConfig:
    """Density control: 3DGS clone/split plus geometry-aware prune and spawn."""

    enabled: bool | None = None
    """Screen-space clone/split; ``None`` lets the plan decide."""
    start_fraction: float = _f(0.25, FRACTION)
    """Density control starts this fraction of the way through the warm-up (:func:`stage_iteration`)."""
    interval: int = _f(100, POSITIVE)
    """Iterations between density-control steps (3DGS's 100). A count, not a fraction: it is the cadence
    at which screen-space gradients are accumulated and acted on, which does not scale with the stage."""
    stop_fraction: float = _f(0.8, Range(0.0, 1.0, lo_open=True))
    """Clone/split stops after this fraction of the warm-up."""
    grad_threshold: float = _f(5e-4, RATE)
    """Mean screen-space gradient norm (NDC units) above which a surfel is cloned or split."""
    max_growth: float = _f(0.5, FRACTION)
    """One clone/split step adds at most this fraction of the current count (largest gradients first)."""
    percent_dense: float = _f(0.01, FRACTION)
    """Surfels larger than this fraction of the extent are split, smaller ones cloned."""
    prune_opacity: float = _f(0.05, FRACTION)
    """Surfels with opacity below this are pruned."""
    opacity_reset_fraction: float = _f(0.75, FRACTION)
    """Opacity resets every this fraction of the warm-up (:func:`stage_iteration`; 0 disables). A reset
    with fewer than 100 warm-up iterations left after it is skipped (the surfels would reach the TSDF
    re-initialisation still transparent)."""
    geometry_prune: bool = True
    """Prune surfels far from the proxy mesh AND of low opacity (co-evolution)."""
    geometry_prune_distance: float = _f(0.02, RATE)
    """"Far" for the geometry-aware prune, fraction of the scene extent."""
    geometry_prune_opacity: float = _f(0.3, FRACTION)
    """"Low opacity" for the geometry-aware prune."""
    geometry_densify: bool = True
    """Proxy faces no surfel covers spawn a surfel (co-evolution)."""
    geometry_densify_voxels: float = _f(0.0, RATE)
    """Which proxy faces no surfel covers: ``> 0``, faces whose centroid is farther than this many
    Poisson grid cells plus two scales of the nearest surfel from every surfel of opacity >= 0.1
    (:meth:`~wtopo.fitting.proxy.ProxyMesh.near_surfels`); 0 (before): faces that are no surfel's
    nearest face, which counts every face beyond the surfel count as a hole (the proxy has more
    faces than there are surfels, and the 2,000 cap is hit at every refresh)."""


@dataclass(kw_only=True)
class RuntimeConfig:
    """Device, reproducibility, checkpoints, progress."""

    device: str = field(default="auto", metadata={"pattern": r"auto|cpu|cuda(:\d+)?"})
    """``"auto"`` (CUDA when available), ``"cpu"`` or ``"cuda:N"``."""
    seed: int = _f(0, Range(0, _SEED_MAX))
    """Seed of torch, NumPy and every random choice of the fit."""
    max_surfels: int | None = _f(None, POSITIVE)
    """Hard cap on the surfel count; ``None``: the plan's (CPU 40,000, CUDA 400,000)."""
    checkpoint_every: int = _f(200, COUNT)
    """Iterations between checkpoints (0: none except at stage ends and on interruption). A count, not a
    fraction: it bounds the work lost to an interruption, whatever the stage length."""
    checkpoint_seconds: float = _f(120.0, RATE)
    """Also checkpoint when this much wall-clock time passed since the last one."""
    keep_checkpoints: int = _f(2, POSITIVE)
    """Checkpoints kept on disk (>= 2)."""
    eval_every: int = _f(200, COUNT)
    """Iterations between history records (losses, and metrics when ground truth exists). A count: it
    sets the cost of evaluation per iteration, which does not depend on the stage length."""
    eval_views: int = _f(4, COUNT)
    """Held-out views for PSNR (taken from the scene's views, not trained on)."""
    eval_metrics: bool = True
    """Compute Chamfer / F-score / PSNR at evaluations when the scene has a ground-truth mesh."""
    usd_every: int = _f(100, COUNT)
    """Write a timeline frame every this many iterations to ``out_dir/timeline.usdc`` (0: none). A
    count, so that frames of runs of different lengths are comparable iteration for iteration."""
    max_consecutive_failures: int = _f(20, POSITIVE)
    """Abort (with a checkpoint) after this many non-finite steps in a row."""
    progress: bool = True
    """tqdm progress bars (also ``fit(progress=...)``)."""
    profile: bool = False
    """Print the time per stage at the end of the fit (total seconds, calls, ms per call, % of the wall
    time; :mod:`wtopo.fitting.profiling`) and store it in the report's ``"profile"``. On CUDA every timed
    section then synchronises the device (slower, but each stage is charged its own kernels); off, no
    section synchronises."""
    image_scale: float | None = _f(None, Range(0.0, 1.0, lo_open=True))
    """Train on images resized by this factor (1.0: full resolution); ``None``: the plan decides
    from the image size and the device."""
    stop_at: int | None = _f(None, COUNT)
    """Stop as if interrupted once this global iteration is reached (time-boxed runs, tests); the
    run resumes from its checkpoint with ``stop_at`` cleared."""
    start_from: str | None = field(default=None, metadata={"pattern": r".+"})
    """A run directory (or its ``checkpoints`` folder) of another fit to branch from: with no checkpoint
    of its own yet, the fit starts from that run's newest checkpoint instead of from scratch, so several
    configurations share one warm-up and differ only by what they change (a paired ablation; on CUDA two
    warm-ups of one seed differ by the order of float atomics). The checkpoint must lie within the warm-up
    (before the TSDF re-initialisation), and the two resolved configurations may differ only in what acts
    after it: :data:`~wtopo.fitting.checkpointing.AFTER_WARMUP`, and the co-evolution's length where
    ``optim.means_decay_iterations`` keeps the source's means' decay horizon
    (:data:`~wtopo.fitting.checkpointing.DECAY_HORIZON`). Make the source with ``stop_at`` at the warm-up's end."""


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
    """Stage 5."""
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    """Density control."""
    losses: LossConfig = field(default_factory=LossConfig)
    """Loss weights."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Proxy mesh."""
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    """Runtime."""
    kind: SceneKind | None = None
    """``OBJECT`` (closed mesh, nothing behind it kept) or ``SCENE`` (background kept at distance, open
    mesh of the region of interest); ``None``: the plan's (object when the scene has masks). See
    :mod:`wtopo.fitting.scene_kind`."""
    sh_degree: int | None = _f(None, Range(0, _SH_MAX))
    """SH degree of the colours (0..3); ``None``: plan (0 for an untextured scene)."""
    background: tuple[float, float, float] | None = _f(None, FRACTION)
    """Background colour behind the surfels; ``None``: the scene's, else plan."""
    filter_sigma: float = _f(0.35, Range(*FILTER_SIGMA_RANGE))
    """Screen-space low-pass of the surfel renderer [pixels] (:class:`wtopo.RasterConfig`; 2DGS uses
    0.71). Half the 2DGS width: a sub-pixel surfel seen edge-on at the silhouette then haloes half
    as far, the fit shrinks the surface less to cancel the halo, and rendered depth stops leaning
    towards the nearest centre (bunny, other settings as before: Chamfer 0.74 % -> 0.44 %; with
    today's defaults see ``benchmarks/fit.md``)."""

    @staticmethod
    def toposurfel_public() -> FitConfig:
        """Settings matching the public TopoSurfel code (design/toposurfel.md) as far as wtopo supports them:
        a long separate initialisation, 1 point per surfel, Poisson without spectral smoothing on the
        initial mesh's box + 10 % at a fine grid with a surface prior, log1p depth loss weight 0.05 (not
        debiased), mesh-normal weight 0, far-from-mesh prune disabled."""
        cfg = FitConfig()
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
        """Inverse of :meth:`to_dict` (a partial dict leaves the other fields at their defaults); an
        unknown key raises ``ValueError`` naming its dotted path, an unknown enum string too."""
        cfg = FitConfig()

        def flat(node: dict, prefix: str):
            for key, value in node.items():
                if isinstance(value, dict):
                    yield from flat(value, f"{prefix}{key}.")
                else:
                    yield f"{prefix}{key}", value

        for path, value in flat(d, ""):
            set_field(cfg, path, value)
        return cfg


def stage_iteration(fraction: float, iterations: int) -> int:
    """The iteration ``fraction`` of the way through a stage of ``iterations`` (nearest; halves round up).

    Schedules are fractions of their stage so that one configuration keeps its shape at any budget:
    with the CPU warm-up of 800 iterations, ``densify.start_fraction = 0.25`` is iteration 200.
    """
    return math.floor(fraction * iterations + 0.5)


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
