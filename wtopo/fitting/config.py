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

_GRID_MIN = 8  # coarser Poisson / TSDF grids cannot resolve any shape
_TSDF_MAX = 2048  # Open3D's TSDF volume is sparse, the Warp one fused in slabs: 2048 per side stays in memory
_POISSON_MAX = 1024  # the Poisson grid is dense (FFT): 1024^3 complex nodes already take 8 GiB per buffer
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
    means_restart: float = _f(0.0, FRACTION, was_bool=True)
    """Restart the means schedule at the co-evolution: it starts at this fraction of ``means`` (never
    below where the single decay stands there) and decays to ``means_final`` at its last iteration.
    ``0`` (the default): one decay over both stages, so the co-evolution starts at ~7e-5 on the CPU
    budget (400 + 200) and moves surfels by < 1 pixel; ``1``: the public code's full restart. Hard
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
    """Iterations (one view each); ``None``: the plan's budget for the device (CPU 400, CUDA 3000)."""


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
    ``None``: the plan's (CPU 8,000; CUDA a quarter of the surfel cap)."""
    backend: TSDFBackend = TSDFBackend.AUTO
    """Fusion of the re-initialisation and the final TSDF mesh: ``AUTO`` (the plan's: Warp on CUDA,
    Open3D on the CPU), ``WARP`` or ``OPEN3D``."""


@dataclass(kw_only=True)
class CoevolutionConfig:
    """Stage 4: surfels and proxy mesh co-evolve; the proxy is rebuilt and the mesh losses applied every iteration."""

    iterations: int | None = _f(None, COUNT)
    """Iterations; ``None``: the plan's budget for the device (CPU 200, CUDA 1000)."""
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
class LossConfig:
    """Loss weights."""

    mask: float | None = _f(None, RATE)
    """Alpha-vs-mask binary cross-entropy weight; ``None``: plan (0.2 when the scene has masks)."""
    normal: float = _f(0.05, RATE)
    """Rendered normal vs depth-derived normal."""
    normal_start_fraction: float = _f(0.5, FRACTION)
    """The normal term is on from this fraction of the warm-up (:func:`stage_iteration`; 2DGS starts it
    late)."""
    distortion: float = _f(100.0, RATE)
    """Depth distortion."""
    distortion_start_fraction: float = _f(0.5, FRACTION)
    """The distortion term is on from this fraction of the warm-up (:func:`stage_iteration`)."""
    scale: float = _f(0.01, RATE)
    """Scale regulariser (anisotropy penalty for 2-scale surfels, shortest-axis for 3)."""
    mesh_depth: float = _f(3.0, RATE)
    """Mesh-depth agreement (co-evolution). 3 with ``mesh_depth_debias`` (was 0.5 without): on the
    hard suite (7 objects x 2 seeds, CPU; ``benchmarks/hard.md``, ``cpu_mesh_depth``) the loop's
    gain against no loop goes from 2.8 % to 5.0 % of the mean Chamfer, every object better (torus
    -9 %, blob -9 %, chair_box -0.2 %); at 10 the torus gains 22 % but the chair's thin parts swell
    and chair_box loses 13 %."""
    mesh_normal: float = _f(0.05, RATE)
    """Mesh-normal agreement (co-evolution)."""
    mesh_start_fraction: float = _f(0.0, FRACTION)
    """The mesh terms are on from this fraction of the co-evolution (:func:`stage_iteration`); the
    proxy still guides signs and density from its first iteration. 0: from the first iteration,
    where their gradient peaks (the method waits 500 of its iterations). 0.25 won on the hard suite's
    screening subset (mean Chamfer 0.614 -> 0.612 %) and lost on the whole suite (0.516 -> 0.518 %:
    bowl, mug, blob_flat worse), so it is off (``benchmarks/hard.md``)."""
    depth_form: DepthLoss = DepthLoss.LOG_RATIO
    """Form of the mesh-depth term."""
    mesh_depth_debias: bool = True
    """The mesh-depth term ignores each view's median offset between the surfels' and the proxy's
    depth (:func:`~wtopo.fitting.losses.mesh_depth_loss` ``debias``): the proxy passes on its shape
    (closed holes, no floaters) but not the inward shift its Poisson smoothing gives convex objects.
    Hard suite mean Chamfer 0.439 -> 0.437 % at weight 0.5, 0.431 -> 0.429 % at weight 3."""
    mesh_depth_robust: float = _f(0.0, RATE)
    """Cauchy scale of the mesh-depth term in Poisson grid cells of the proxy
    (:func:`~wtopo.fitting.losses.mesh_depth_loss` ``robust``): pixels where the surfels and the
    proxy disagree by more than this pull less and less (a thin part the proxy's smoothing swelled);
    0: the plain absolute value (the default). Hard suite, 7 objects x 2 seeds (``benchmarks/hard.md``,
    ``cpu_robust``): the loop's gain against no loop falls from 5.0 % to 4.3 % at scale 1 (chair_box
    better, the torus and the blob 2-3 % worse) and to 4.3 % at scale 1 with weight 5 (bowl and mug
    worse): the large disagreements it discounts are the ones that help the smooth objects."""
    mesh_depth_robust_behind: bool = False
    """With ``mesh_depth_robust``: the Cauchy form only where the surfels lie behind the proxy (its pull
    towards the camera, which swells a thin part the proxy's smoothing thickened); where they lie in front
    (floaters, bumps) the plain term pulls in full, and disagreements under the scale pull as before
    (:func:`~wtopo.fitting.losses.mesh_depth_loss` ``robust_behind``). Off: on the ten-view scenes on the
    CUDA budget (``benchmarks/hard.md`` ``gpu_sparse3``) it left the chair 8-12 % worse than no loop, where
    the two-sided form at 3 cells brought it within 2 %: the chair's loss is on the other side (surfels in
    front of a proxy that lost its thin parts), which is also where the floaters the loop should pull in
    lie."""
    mesh_depth_behind: float = _f(1.0, FRACTION)
    """Weight of the mesh-depth term on pixels where the surfels lie behind the proxy after the
    debias (:func:`~wtopo.fitting.losses.mesh_depth_loss` ``behind``): there the proxy pulls them
    towards the camera, which is what swells a thin part the Poisson smoothing thickened and lifts a
    concavity's floor towards the lid the proxy puts over it; pixels where the surfels lie in front
    (floaters, bumps) keep the full weight. 1: symmetric (the default). At 0.3 every object of the hard
    suite got worse (CPU, ``benchmarks/hard.md`` ``cpu_behind03``: mean Chamfer +6.8 %, torus +12 %, bowl
    +11 %): the loop pays at the CPU by pulling the surface outwards against the fit's shrink."""
    mesh_photo_gate: float = _f(0.0, RATE)
    """The mesh terms leave out the pixels where the surfels' depth and the proxy's differ by more than
    this many proxy grid cells and the neighbouring photographs prefer the surfels' depth (their window,
    through each depth with the surfels' normal, correlates better by 0.1 in ``1 - NCC`` with the same two
    neighbours: :meth:`~wtopo.fitting.multiview.MultiViewNCC.prefers`): a thin part the proxy's
    smoothing lost, or a concavity it lidded, is not pulled towards the proxy; where the photographs
    do not say (no texture, no neighbour, a floater's inconsistent depth) the proxy pulls as before.
    0 turns the gate off (the default). At 3 cells on the CPU hard suite (``benchmarks/hard.md``
    ``cpu_photogate3``, 9 scenes x 2 seeds) the mean Chamfer is unchanged (-0.02 %): the chairs gain about
    1 %, the bowl loses about 1 %. On the device (``gpu_photogate2``) the dense objects at 512 px are
    unchanged (-14.0 % per case against no loop, the loop -13.7 %) and the ten-view chair's loss to the
    loop is halved but stays over 2 % on one seed, the ten-view cup worse on one seed: off."""
    mesh_inset: int = _f(0, COUNT)
    """The mesh terms skip the pixels within this many pixels of the edge of the pixels they compare
    (the surfels' coverage where the proxy is hit), eroded by a ``(2 inset + 1)^2`` square: a part
    narrower than ``2 inset + 1`` pixels in a view (a thin leg the coarse proxy thickens) gets no pull
    from it there, while a broad surface keeps it away from its rim. 0: every compared pixel (the
    default). At 2 (CPU, ``benchmarks/hard.md`` ``cpu_inset2``) chair_box gains 1 % and the torus loses
    6 %: a smooth object's rims carry the proxy's outward pull."""
    mesh_depth_source: RenderedDepth = RenderedDepth.MEDIAN
    """Surfel depth compared with the mesh depth (``EXPECTED`` averages in semi-transparent layers
    behind the surface and drags the proxy inwards: bunny Chamfer 0.281 %
    against 0.262 % with the median, ``benchmarks/fit.md``)."""
    multiview: float | None = _f(None, RATE)
    """Multi-view photometric consistency (:mod:`wtopo.fitting.multiview`, PGSR's patch NCC): each
    training view's rendered plane at sampled pixels is warped into two neighbouring photographs and
    scored by ``1 - NCC``; 0 turns it off. ``None``: the plan's (0.15 when the photographs have
    texture, 0 for shading-only captures; ``benchmarks/hard.md``, ``benchmarks/real.md``)."""
    multiview_start_fraction: float = _f(0.5, FRACTION)
    """The multi-view term is on from this fraction of the warm-up (:func:`stage_iteration`)."""
    multiview_geometric: float = _f(0.0, RATE)
    """Multi-view geometric consistency (:mod:`wtopo.fitting.geometric`, PGSR's forward-backward
    reprojection): sampled pixels of each training view are carried by its rendered depth into a
    neighbouring view and back by that view's rendered depth (rendered without gradient); the loss
    is the round-trip error in pixels (pixels missing by 1 px or more carry none), from
    ``multiview_start_fraction`` of the warm-up on. 0 turns it off (the default). Its pixels are
    ``multiview_pixels``; it needs no texture, so the plan's texture rule for ``multiview`` does not
    apply to it. At PGSR's weight 0.03 it made every object of the hard suite worse (mean Chamfer
    0.437 -> 0.491 %, blob and mug +28-29 %; ``benchmarks/hard.md``, ``cpu_geometric``)."""
    multiview_pixels: int = _f(4096, COUNT)
    """Reference pixels drawn per iteration for the multi-view term (each a 7 x 7 window)."""
    silhouette_band: int = _f(0, COUNT)
    """With masks: pixels within this many pixels of the mask boundary are left out of the
    photometric and mask terms (0 keeps them). A mask and an image rendered one ray per pixel say
    nothing sub-pixel about where the boundary lies, while splats pay for every fraction of a pixel
    of halo there. On the bunny (3 seeds, ``benchmarks/fit.md``) a 2-pixel band lowers Chamfer a
    little (0.262-0.274 % against 0.272-0.277 %) but costs F-score (0.88 against 0.95) and 1.8 dB
    of PSNR, so it is off by default."""
    mask_halo: bool = False
    """With masks: the mask term's target outside the mask is the opacity the renderer's low-pass
    draws around centres lying exactly on the silhouette (:func:`~wtopo.fitting.losses.halo_target`:
    0.44 on the first ring of pixels at ``filter_sigma`` 0.35) instead of 0, and those ring pixels
    are left out of the photometric term, so neither term pulls the centres inside the silhouette to
    cancel the halo. Hard suite, one seed (``benchmarks/hard.md``, ``cpu_halo``): it halves the smooth
    objects' shrink (torus 0.185 -> 0.116 %, inward offset +0.187 -> +0.109; blob 0.343 -> 0.226 %) but
    fattens the thin, boxy chair (0.129 -> 0.139 %, chair_box 0.130 -> 0.150 %), the mug comes out at
    0.704 % (0.499 %), the 7 objects' mean is unchanged (0.437 -> 0.439 %) and held-out PSNR drops
    1.5 dB (the halo the target asks for is not in the photographs): off by default."""


@dataclass(kw_only=True)
class MeshConfig:
    """The differentiable proxy mesh (oriented points -> Poisson -> marching cubes)."""

    resolution: int | None = _f(None, Range(_GRID_MIN, _POISSON_MAX))
    """Poisson grid resolution (nodes per side); ``None``: the plan's (CPU 64; CUDA from the pixel
    footprint, 128-256)."""
    sigma: float = _f(1.0, RATE)
    """Spectral smoothing of the Poisson solve, in grid cells (0 = none)."""
    padding: float = _f(0.1, FRACTION)
    """Poisson domain padding, fraction of the unit cube."""
    samples_per_surfel: int = _f(5, (1, 5))
    """Oriented points per surfel: 1 (centre) or 5 (centre + 4 tangent offsets)."""
    offset: float = _f(0.5, RATE)
    """Tangent offset of the extra samples, in surfel sigmas."""
    offset_weight: float = _f(0.5, RATE)
    """Weight of the extra samples relative to the centre."""
    normal_flip: NormalFlip = NormalFlip.MESH
    """Normal sign rule (mesh | view | random)."""
    sign_distance: float = _f(3.0, RATE)
    """Mesh-guided signs: a surfel not made on a mesh triangle takes its nearest proxy face's normal
    side when that face is closer than this many of the surfel's in-plane sigmas (its larger scale),
    the cameras' side otherwise; surfels made on a triangle (the TSDF scaffold, a spawn) keep its sign
    (:func:`~wtopo.fitting.densify.align_normal_signs`). Before: every surfel took the face's side
    within a fixed 0.02 of the scene extent and the cameras' side elsewhere, which flipped 37 % of the
    hard suite's ``chair_ground`` scaffold surfels and moved its proxy from 1.1 % to 7.8 % of the
    diagonal off the truth (``benchmarks/hard.md``)."""
    opacity_threshold: float = _f(0.0, FRACTION)
    """Surfels below this opacity do not contribute oriented points."""
    poisson_box: PoissonBox = PoissonBox.UNIT
    """Domain of the Poisson solve."""
    surface_prior: float = _f(0.0, RATE)
    """Weight of a surface prior splatted from the TSDF mesh into the Poisson input (public code: on)."""
    silhouette_gain: float = _f(0.0, FRACTION)
    """Scenes with masks: each co-evolution iteration the proxy's ray-cast silhouette in the training
    view is compared with the view's mask, and this fraction of the distance by which it lies inside
    (pixels missed minus pixels covered outside, per boundary pixel, times the footprint at the rim)
    is added to a running offset that moves the proxy's vertices along their normals (at most two
    Poisson grid cells; :mod:`wtopo.fitting.silhouette`), so the mesh terms pull the surfels out to
    the masks (their soft rim covers the masks while their centres sit inside). 0 turns it off (the
    default). Hard suite, one seed (``benchmarks/hard.md``, ``cpu_silhouette``): at gain 0.1 with the
    default mesh-depth weight 0.5 it moves nothing (the surfels do not follow); at 0.3 with
    ``losses.mesh_depth=3`` the loop lowers the 7 objects' mean Chamfer by 4.0 % against no loop (the
    default loop: 2.9 %; the blob and the torus gain 24 % and 9 %) but the mug loses 9 %: not a default."""
    curvature_compensation: bool = False
    """Move each proxy vertex along its normal by ``(sigma^2 + 1/6) h^2 (H - H_mean)`` (at most half a
    cell ``h``): the shift by which the smoothed Poisson indicator and its level put curved parts
    inside and flat parts outside the points (:mod:`wtopo.fitting.curvature`)."""
    support_voxels: float = _f(0.0, RATE)
    """Proxy faces whose centroid lies farther than this many Poisson grid cells, plus twice the
    larger scale of the nearest surfel, from every surfel centre of opacity >= 0.1 are unsupported:
    surface the Poisson solve closes over where no surfel is (the far side of a cut-open floor, the
    inside of an opening). The mesh terms skip the pixels that see them and geometry-aware
    densification spawns nothing on them. 0: every face is supported."""


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
    with the CPU warm-up of 400 iterations, ``densify.start_fraction = 0.25`` is iteration 100.
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
