# SPDX-License-Identifier: Apache-2.0
"""The loss terms and the proxy mesh of :class:`~wtopo.fitting.config.FitConfig` (``losses`` and ``mesh``),
re-exported by :mod:`wtopo.fitting.config`."""

from __future__ import annotations

from dataclasses import dataclass

from .config_kinds import (
    _GRID_MIN,
    _POISSON_MAX,
    COUNT,
    FRACTION,
    RATE,
    DepthLoss,
    NormalFlip,
    PoissonBox,
    Range,
    RenderedDepth,
    _f,
)

__all__ = ["LossConfig", "MeshConfig"]


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
    mesh_end_fraction: float = _f(1.0, FRACTION)
    """The mesh terms are off from this fraction of the co-evolution on (:func:`stage_iteration`), so its
    last part refines the surfels on the photographs alone while the proxy still guides signs and
    density. 1: on to the end (the default). Must exceed ``mesh_start_fraction``. 0.5 at the CPU budget
    (800 + 400, 17 cases of the hard suite; ``benchmarks/hard.md``, ``cpu_end05``): every chair case within
    1 % of no loop (the default loop: up to +4.9 %), but the smooth objects keep only half to two thirds of
    their gain (-5.4 % against no loop on the mean, the default -7.2 %), so it is not the default."""
    mesh_thin_limit: float = _f(0.15, FRACTION)
    """The thin-part rule (:mod:`~wtopo.fitting.thin_parts`): when, at the co-evolution's start, more than
    this fraction of the proxy's pixels (8 training views) look through a part under ``2 mesh.sigma + 1``
    Poisson cells thick (there the proxy is the splat's blend of a part's two sides), the proxy's grid
    doubles for the co-evolution (up to 256 per side) and is measured again; still over it, the mesh terms
    stay off for the fit (the proxy still guides signs and density). 1: never (the share is still
    measured and reported). At the CPU default (64^3 proxy, 128 px; ``benchmarks/hard.md``, ``cpu_thin``)
    the three chairs read 0.28-0.34, every other suite scene 0.07 or less (the mug and the ten-view cup
    0.06-0.07, the bowl and the bunny 0.05, the torus 0.03); 0.15 lies between. On the doubled 128^3 grid
    the chairs read 0.06-0.08, their mesh terms run, and they go from +2.1 % to -0.7 % against no loop
    (``cpu_thin128``). On the CUDA budget's 128^3 proxy the rule does not fire."""
    mesh_thin_probe: int | None = _f(None, Range(_GRID_MIN, 256))
    """Nodes per side of the grid the thin-part rule first measures on; ``None``: the proxy's own (the
    default, as measured on the suite). A part's thickness in cells depends on the grid, so the CUDA
    settings' finer proxy (256^3 at 512 px) reads the chairs as thick where the CPU default's 64^3 reads them
    thin; 64 classifies scenes alike on every device. When the probe fires and the proxy already has at
    least twice the probe's nodes, the proxy keeps its grid, its own share decides the mesh terms, and the
    fit counts as refined (``optim.means_thin_decay`` applies); otherwise the grid doubles from the probe's
    as without it. Measured at the GPU settings (512 px, ``benchmarks/hard.md``, ``gpu_probe``): 64 fires on
    the three chair scenes and makes every one worse, +2 to +19 % Chamfer against the default at 3,000 + 1,000
    and worse than no loop; so it stays off."""
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
    mesh_view_support: int = _f(0, COUNT)
    """The mesh terms leave out the pixels whose surfel point (the rendered median depth along the pixel's
    ray) fewer than this many training views see, the pixel's own view included
    (:mod:`~wtopo.fitting.view_support`: another view sees the point when it projects onto a pixel of that
    view rendered opaque at the same depth within ``2`` proxy cells). One photograph does not fix a
    surface's depth and the proxy's guess there (the lid the Poisson surface puts over a cup's unseen
    inside) is no better, so such pixels are not pulled towards it. 0 or 1: every compared pixel (the
    default). At 2 on the device (``benchmarks/hard.md`` ``gpu_view_support``, 512 px) it leaves out 7-8 %
    of the ten-view cup's pixels, 0.1-5 % of the other ten-view scenes' and under 0.1 % on 64 views, and
    moves no scene beyond the spread between fits (the cup +1.6 % against no loop over twelve fits, the
    loop +1.2 %): off. The share it leaves out is in the fit's history when on."""
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
    level_sigma: float | None = _f(None, RATE)
    """The Poisson proxy's zero level: 0 shifts the indicator by one level, its weighted mean at the points,
    which suits a closed object; over 0 by a local one, its mean at the points under a Gaussian of this
    many grid cells (:func:`wtopo.poisson.poisson_indicator`'s ``level_sigma``), so an open sheet (a
    ground the region of interest cuts) keeps its zero crossing on its points beside a closed part.
    ``None``: the plan's (scenes 2, objects 0)."""
    clip_to_region: bool | None = None
    """Build the proxy from the oriented points within two Poisson cells of the region of interest and keep
    only its faces within one cell of it (:class:`~wtopo.fitting.proxy.ProxyMesh`'s ``clip``): outside the
    region a scene's surfels are background no mesh orients, and its proxy is the Poisson solve's closing
    (the periodic image of a ground the region cuts lies over the region and hides it from the cameras).
    ``None``: the plan's (scenes yes, objects no)."""
    support_voxels: float = _f(0.0, RATE)
    """Proxy faces whose centroid lies farther than this many Poisson grid cells, plus twice the
    larger scale of the nearest surfel, from every surfel centre of opacity >= 0.1 are unsupported:
    surface the Poisson solve closes over where no surfel is (the far side of a cut-open floor, the
    inside of an opening). The mesh terms skip the pixels that see them and geometry-aware
    densification spawns nothing on them. 0: every face is supported."""
