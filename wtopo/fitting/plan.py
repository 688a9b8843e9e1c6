# SPDX-License-Identifier: Apache-2.0
"""The stage plan: which parts of the fit a scene needs, each decision with its reason.

The plan is decided from the scene (masks, background, texture, view count, image size, device)
and the configuration; a configuration field that is set (not ``None``) overrides the plan's
choice and the plan says so. It is printed at the start of :func:`wtopo.fit` and stored in
``FitResult.plan`` and ``plan.json``.
"""

from __future__ import annotations

import numpy as np
import torch

from . import presets as _presets
from ._image_stats import as_np, texture_std, view_inconsistency, window_std
from ._plan_types import Plan, _Decisions
from .config import FitConfig, InitSource, Preset
from .scene_kind import SceneKind, analyse_layout

__all__ = ["Plan", "make_plan", "resolve_config", "split_views", "views_per_point"]

_TEXTURE_STD = 0.02  # colour std (in [0,1] units) below which the foreground counts as untextured
_VIEW_CONSISTENCY = 0.04  # mean reprojected colour difference below which the scene counts as diffuse
_MIN_SH_VIEWS = 20  # fewer views than this cannot constrain view-dependent colour
_VIEW_DEPENDENT_SH = 3  # SH degree where view-dependent colour is found or cannot be ruled out: 3DGS's and 2DGS's
_MIN_EVAL_VIEWS = 12
# Per-device budgets and rules below: the measurements behind each value are in design/decisions.md. The
# iterations, image-size cap and grid ranges are the preset's (wtopo.fitting.presets).
# The share of the co-evolution over which the means' single decay still runs (the plan sets
# optim.means_decay_iterations = warm-up + this share of the co-evolution); the rest keeps means_final.
# CUDA 0.5: the loop's fits better on 13 of 14 suite scenes than at 3,000 + 1,000. None (CPU): the whole fit.
_MEANS_DECAY_COEVO = {"cpu": None, "cuda": 0.5}
# The co-evolution's means restart (optim.means_restart, a fraction of optim.means). CUDA 0.0625 (1e-4): the
# loop's fits -3.7 % on the suite's mean at 512 px. The CPU keeps none: 0.3 swelled the chairs 15-24 %.
_MEANS_RESTART = {"cpu": 0.0, "cuda": 0.0625}
# The renderer's screen-space low-pass (filter_sigma) [pixels]. CUDA 0.25: +0.07 dB held-out PSNR on the mean
# of eight peers-suite fits (DTU +0.25 over two seeds, the masked objects +0.17, the unmasked synthetic scenes
# -0.06) and closer meshes on two of three objects. The CPU keeps 0.35: at its smaller training images 0.25 was
# level on the mean (-0.10 to +0.11 dB by scene).
_FILTER_SIGMA = {"cpu": 0.35, "cuda": 0.25}
# CPU: the preset's base budget covers this many training pixels to fit (unmasked pixels at the trained image
# scale: twice the default bunny's 109k); a capture with more (an unmasked scene: every pixel is
# ground, background or sky) gets proportionally more iterations, as long as the warm-up renders at
# most _CPU_RENDER_PIXELS pixels (1,250 views of 160 x 120: a few minutes on 2 cores).
_CPU_FIT_PIXELS = 250_000
_CPU_RENDER_PIXELS = 24_000_000
# Density control every warm-up / _DENSIFY_STEPS iterations within _DENSIFY_INTERVAL: the 800-iteration CPU warm-up
# keeps its 100; shorter presets keep about as many density steps instead of one or two
_DENSIFY_STEPS = 8
_DENSIFY_INTERVAL = (10, 100)
_MAX_SURFELS = {"cpu": 40_000, "cuda": 400_000}
# Faces of the TSDF re-initialisation mesh (one surfel each): _REINIT_DENSITY faces per squared pixel
# footprint of the region of interest's box surface (each surfel starts about a footprint across), between
# _REINIT_MIN and the device's cap. A fixed cap put sub-pixel surfels on the surface at 128 px, and the mesh
# terms then swelled parts a few pixels thick (the chair 17-20 % worse with the loop than without).
_REINIT_DENSITY = 0.25
_REINIT_MIN = 8000
# Fewer faces where fewer views see the surface: the density above (measured on 32-view sphere rigs, which
# see a point of their region's surface from ~12 views: views_per_point) is scaled by
# min(1, views per point / _REINIT_VIEWS); ten views (3.7-3.8 per point) get 0.33 of it.
_REINIT_VIEWS = 11.5
_VIEW_FACING = 0.25  # a view sees a point of the region's surface when it faces it within ~75 degrees
_REINIT_FACES = {"cpu": _REINIT_MIN, "cuda": _MAX_SURFELS["cuda"] // 4}  # caps (CUDA: room to densify)
_PROXY_FOOTPRINTS = 2.0  # proxy grid cell ~ 2 pixel footprints (a finer Poisson grid only adds noise)
_SCENE_LEVEL_SIGMA = 2.0  # a scene proxy's local zero level, Poisson cells (poisson_indicator's level_sigma)
# final TSDF voxel in pixel footprints: 0.8, and half that where the co-evolution finds thin parts
# (FitRun._final_mesh); finer voxels fuse the rendered depth's sub-pixel noise into the surface
# (design/decisions.md, "final voxel")
_FINAL_FOOTPRINTS = 0.8
_REINIT_GRID_MAX = 128  # the re-initialisation's TSDF voxels at most (its mesh is decimated to tsdf.max_faces)
_MASK_WEIGHT = 0.2  # alpha-vs-mask BCE weight: 0.5 pulls the surface in, 0 leaves short fits semi-transparent

_MULTIVIEW_WEIGHT = 0.15  # PGSR's multi-view NCC weight
# median 7x7 grey std below which the multi-view term is left out (measured: the flat-albedo blob 0.009,
# every textured scene of the suite and the rigs >= 0.043)
_MULTIVIEW_TEXTURE = 0.02
def split_views(scene, eval_views: int) -> tuple[list[int], list[int]]:
    """``(training, held-out)`` camera indices of ``scene`` as the fit splits them: the scene's own test
    split, else ``eval_views`` evenly spaced views held out (neither end; fewer when ``eval_views``
    approaches the view count), else none held out."""
    n = len(scene.cameras)
    test_idx = getattr(scene, "test_indices", None)
    if test_idx is not None and len(test_idx):
        test = [int(i) for i in test_idx]
        train_idx = getattr(scene, "train_indices", None)
        return [int(i) for i in (range(n) if train_idx is None else train_idx) if int(i) not in test], test
    if eval_views:
        test = sorted({int(round(x)) for x in np.linspace(0, n - 1, int(eval_views) + 2)[1:-1]})
        return [i for i in range(n) if i not in test], test
    return list(range(n)), []


def _eval_views(scene, cfg: FitConfig) -> tuple[int, str]:
    """``(held-out views, reason)``: the scene's test split, else ``runtime.eval_views`` when there are at
    least ``_MIN_EVAL_VIEWS`` views, else none."""
    n = len(scene.cameras)
    test = getattr(scene, "test_indices", None)
    if test is not None and len(test):
        return len(test), f"the scene's {len(test)} held-out views"
    k = int(cfg.runtime.eval_views) if n >= _MIN_EVAL_VIEWS else 0
    return k, (f"{n} views: {k} held out for PSNR" if k else
               f"only {n} views: all used for training, PSNR on training views")


def make_plan(scene, cfg: FitConfig, device: torch.device) -> Plan:
    """Decide the stage plan for ``scene`` (in the internal frame) under ``cfg`` on ``device``."""
    plan = _Decisions()
    rng = np.random.default_rng(cfg.runtime.seed)
    n_eval, eval_why = _eval_views(scene, cfg)
    train_idx = split_views(scene, n_eval)[0]
    n_views = len(train_idx)
    # the image statistics below read the photographs the fit trains on, never the held-out ones (the
    # normalisation and the region of interest still come from every view: analyse_layout)
    seen = scene.subset(train_idx) if 0 < n_views < len(scene.cameras) else scene
    images = as_np(seen.images)
    masks = as_np(getattr(seen, "masks", None))
    depths = as_np(getattr(seen, "depths", None))
    points = getattr(scene, "points", None)
    has_masks = masks is not None
    bg = getattr(scene, "background", None)

    plan.set("device", str(device), "CUDA available" if device.type == "cuda" else
             ("CPU requested" if cfg.runtime.device == "cpu" else "no CUDA device"))

    # -- what the capture is: object or scene, region of interest
    layout = analyse_layout(scene, cfg.kind)
    plan.layout = layout
    plan.set("scene_kind", layout.kind.value, layout.reason)
    plan.set("region_of_interest", [np.round(layout.roi_lower, 4).tolist(), np.round(layout.roi_upper, 4).tolist()],
             f"from {layout.roi_source} (internal frame)")
    is_scene = layout.kind is SceneKind.SCENE
    plan.set("mesh_policy", "open_roi" if is_scene else "watertight",
             f"scene: the region of interest's surface, open where unobserved, no face within "
             f"{layout.near:.3g} of a camera; components kept by view support" if is_scene else
             "object: closed surface; every component the views support is kept (never by rank)")

    # -- initialisation
    n_pts = 0 if points is None else len(points)
    if n_pts >= 100:
        src, why = "points", f"the scene has {n_pts} points"
    elif is_scene and n_views >= 2:
        src, why = "mvs", (f"the scene has {n_pts} points (< 100) and no masks: plane-sweep stereo over the "
                           "training views, depths confirmed by their neighbours")
    else:
        src, why = "cameras", (f"the scene has {n_pts} points (< 100): random points in the cameras' common volume"
                               + (" (the masks' visual hull)" if has_masks else ""))
    plan.set("init_source", src, why, None if cfg.init.source == "auto" else cfg.init.source)

    # -- masks and background
    plan.set("mask_loss", _MASK_WEIGHT if has_masks else 0.0,
             "object masks given: alpha supervised by the mask" if has_masks
             else "no masks",
             cfg.losses.mask)
    plan.set("background_rule", is_scene,
             "object: nothing behind it to keep" if not is_scene
             else "scene: contracted steps outside the region of interest, nothing on a lens, background spared by "
                  "the geometry-aware prune; a TSDF re-initialisation keeps the surfels far from its mesh")
    n_bg = int(cfg.init.num_points) if is_scene else 0
    plan.set("background_points", n_bg,
             "scene: surfels on shells beyond the cameras hold the background at distance" if is_scene
             else "object: no background", cfg.init.background_points)
    if bg is not None:
        bg_val, why = tuple(float(c) for c in bg), "the scene's background colour"
    else:
        bg_val, why = (0.0, 0.0, 0.0), "no background given: black"
    plan.set("background", bg_val, why, None if cfg.background is None else tuple(cfg.background))

    # -- colour model
    tex = texture_std(images, masks)
    if tex < _TEXTURE_STD:
        deg, why = 0, f"untextured (foreground colour std {tex:.3f} < {_TEXTURE_STD})"
    elif n_views < _MIN_SH_VIEWS:
        deg, why = 0, f"{n_views} training views (< {_MIN_SH_VIEWS}) cannot constrain view-dependent colour"
    elif depths is not None:
        inc = view_inconsistency(seen, images, depths, rng)
        if np.isfinite(inc) and inc < _VIEW_CONSISTENCY:
            deg, why = 0, f"diffuse: reprojected colours differ by {inc:.3f} (< {_VIEW_CONSISTENCY}) between views"
        else:
            deg, why = _VIEW_DEPENDENT_SH, f"view-dependent colour: reprojected colours differ by {inc:.3f}"
    else:
        deg, why = _VIEW_DEPENDENT_SH, (f"textured (colour std {tex:.3f}), {n_views} training views and no depth to "
                                        "test view dependence: the degree of 3DGS and 2DGS")
    plan.set("sh_degree", deg, why, cfg.sh_degree)

    # -- multi-view consistency (PGSR's patch NCC): it needs texture that windows can match
    wstd = window_std(images, masks)
    if n_views < 2:
        mv, why = 0.0, "one view: no neighbour to compare with"
    elif wstd < _MULTIVIEW_TEXTURE:
        mv, why = 0.0, (f"shading only (median 7x7 grey std {wstd:.4f} of unclipped windows < {_MULTIVIEW_TEXTURE}): "
                        "windows do not match between views (flat-albedo blob: Chamfer 0.34 -> 0.50 % with the term)")
    else:
        mv, why = _MULTIVIEW_WEIGHT, (f"textured (median 7x7 grey std {wstd:.3f} of unclipped windows): patch NCC "
                                      "against two neighbouring views from mid warm-up")
    plan.set("multiview", mv, why, cfg.losses.multiview)

    # -- density control
    dens = src == "cameras" or n_pts < 2000 or is_scene
    if is_scene:  # the background covers every pixel: a coverage gap never opens
        why = "scene: clone/split by screen-space gradient (3DGS) at every density step of the warm-up"
    elif dens:
        why = "sparse initialisation: clone/split while coverage gaps exist"
    else:
        why = f"{n_pts} initial points: clone/split only while coverage gaps exist"
    plan.set("densify", dens, why, cfg.densify.enabled)

    # -- image size and budgets: the preset's
    preset = Preset(cfg.preset)
    b = _presets.budget(preset, device)
    plan.set("preset", preset, f"{preset.value}: {b.iterations[0]} + {b.iterations[1]} base iterations, images "
             f"up to {b.max_side} px, proxy grid {b.proxy_grid[0]}-{b.proxy_grid[1]}, final grid "
             f"{b.final_grid[0]}-{b.final_grid[1]}"
             + (f", proxy and mesh terms every {b.mesh_every} co-evolution iterations" if b.mesh_every > 1 else "")
             + f" on {device.type}")
    h, w = images.shape[1:3]
    plan.set("image_scale", default_image_scale(h, w, device, preset),
             f"{w}x{h} images; longest side capped at {b.max_side} px by the {preset.value} preset on {device.type}",
             cfg.runtime.image_scale)
    _budget(plan, scene, cfg, device, layout, float(plan["image_scale"]))

    # -- held-out views
    plan.set("eval_views", n_eval, eval_why)

    # -- stages
    if int(plan["coevolution_iterations"]) == 0:
        loop, why = False, "no co-evolution iterations"
    elif is_scene:
        loop, why = False, ("scene: the Poisson proxy would close the open surface the region of interest cuts, "
                            "where no view supports it, and pull the surfels there")
    else:
        loop, why = True, "object: proxy mesh rebuilt and supervising the surfels"
    plan.set("mesh_loop", loop, why, cfg.coevolution.enabled)
    coevo_it = int(plan["coevolution_iterations"])
    if plan["mesh_loop"] and b.polish > 0:
        polish, why = round(b.polish * coevo_it), (
            f"{b.polish:g} of the co-evolution's iterations ({preset.value}): the proxy's pull costs the surfels "
            "held-out PSNR and pulls the mesh over concave places; training on the photographs alone before the "
            "final mesh gives both back")
    elif plan["mesh_loop"]:
        polish, why = 0, f"{preset.value}: none (the mesh is the result; the surfels stay as the loop left them)"
    else:
        polish, why = 0, ("no proxy-mesh loop to release the surfels from (on unbounded scenes a polish lowered "
                          "held-out PSNR: bunny_env 28.68 -> 28.50 dB, chair_env 29.93 -> 29.89 on the CPU)")
    plan.set("polish_iterations", polish, why, cfg.polish.iterations)
    covered = h * w * float(plan["image_scale"]) ** 2 * (float(masks.mean()) if has_masks else 1.0)
    n_it = int(plan["warmup_iterations"]) + coevo_it + int(plan["polish_iterations"])
    mesh_terms = cfg.losses.mesh_depth > 0 or cfg.losses.mesh_normal > 0  # else the loop builds no proxy
    builds = -(-coevo_it // b.mesh_every) if plan["mesh_loop"] and mesh_terms else 0
    stereo = InitSource(plan["init_source"]) is InitSource.MVS
    plan.set("expected_seconds", round(_presets.expected_seconds(preset, device, n_it, covered, proxy_builds=builds,
                                                                 stereo=stereo)),
             f"{n_it} iterations covering {covered / 1e3:.0f}k pixels a view, {builds} proxy builds"
             f"{', the stereo' if stereo else ''}, at the {preset.value} preset's measured cost on "
             f"{'one H100' if device.type == 'cuda' else f'{torch.get_num_threads()} CPU threads'} (a planning figure)")
    if is_scene and not plan["mesh_loop"]:
        reinit, why = False, ("scene without the proxy-mesh loop: nothing would use a re-initialised scaffold, and "
                              "replacing the warm-up's surfels cost DTU scan24 6.0 dB held-out PSNR that the "
                              "co-evolution did not win back (25.40 -> 19.37 -> 25.13 dB on an H200)")
    else:
        reinit, why = True, ("re-initialise from fused surfel depth between warm-up and co-evolution: the proxy "
                             "loop starts from its scaffold" if plan["mesh_loop"] else
                             "re-initialise from fused surfel depth between warm-up and co-evolution (object: the "
                             "components the views support)")
    plan.set("tsdf_reinit", reinit, why, cfg.tsdf.enabled)
    if is_scene:
        lvl, why = _SCENE_LEVEL_SIGMA, (f"scene: the proxy's zero level is local ({_SCENE_LEVEL_SIGMA:g} cells), so "
                                        "a ground the region of interest cuts keeps its crossing beside closed parts")
    else:
        lvl, why = 0.0, "object: one closed surface, one level"
    plan.set("proxy_level_sigma", lvl, why, cfg.mesh.level_sigma)
    plan.set("proxy_clip", is_scene, "scene: the proxy's faces outside the region of interest are the Poisson "
             "solve's closing and are dropped" if is_scene else "object: the whole proxy is the object",
             cfg.mesh.clip_to_region)
    plan.set("gt_metrics", getattr(scene, "gt_mesh", None) is not None and cfg.runtime.eval_metrics,
             "ground-truth mesh given: Chamfer / F-score at evaluations" if getattr(scene, "gt_mesh", None)
             is not None else "no ground-truth mesh")
    return plan.build()


def _footprint(scene, layout, image_scale: float) -> float:
    """Median pixel footprint at the region of interest's centre [internal units]: the distance of
    each camera to it over the focal length of the images actually trained on."""
    fp = [float(np.linalg.norm(c.center - layout.roi_center)) / (float(c.K[0, 0]) * image_scale)
          for c in scene.cameras]
    return float(np.median(fp))


def views_per_point(scene, layout, samples: int = 512) -> float:
    """Mean number of training views that see a point of the region of interest's surface (float).

    The surface is the ellipsoid inscribed in the region's box (``layout.roi_lower`` / ``roi_upper``,
    internal units), sampled at ``samples`` Fibonacci directions with their outward normals. A view sees
    such a point when the region's centre projects inside its image in front of it and the direction
    from the centre to the view is within ``_VIEW_FACING`` (cosine) of the point's normal; occlusion is
    not tested, and neither is the frame's edge at the point (a loose region from few masks would lose
    views it does not lose). Directions no view sees (under a hemisphere rig, behind a forward-facing
    one) are left out of the mean. Only the cameras' poses, intrinsics and the training split are read:
    any frame, no images. 0.0 when no view sees the region."""
    k = np.arange(samples, dtype=np.float64) + 0.5
    polar = np.arccos(1.0 - 2.0 * k / samples)
    azim = np.pi * (1.0 + 5.0 ** 0.5) * k
    u = np.stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar), np.cos(polar)], axis=1)
    half = np.maximum(0.5 * (np.asarray(layout.roi_upper, np.float64) - np.asarray(layout.roi_lower, np.float64)),
                      1e-12)
    normals = u / half
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    center = np.asarray(layout.roi_center, np.float64)
    train = scene.train_indices if scene.train_indices is not None else range(len(scene.cameras))
    count = np.zeros(samples)
    for i in train:
        cam = scene.cameras[int(i)]
        uv, z = cam.project(center[None])
        if not (z[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height):
            continue
        to_cam = cam.center - center
        count += normals @ (to_cam / max(float(np.linalg.norm(to_cam)), 1e-300)) > _VIEW_FACING
    seen = count[count > 0]
    return float(seen.mean()) if seen.size else 0.0


def _fit_pixels(scene, image_scale: float) -> tuple[float, float]:
    """``(pixels to fit, pixels per view)`` at the trained scale: the training views' mask pixels
    (every pixel without masks) and one view's pixels."""
    train = scene.train_indices if scene.train_indices is not None else range(len(scene.cameras))
    train = [int(i) for i in train]
    h, w = (int(x) for x in scene.images.shape[1:3])
    per_view = h * w * image_scale ** 2
    masks = getattr(scene, "masks", None)
    cover = len(train) if masks is None else float(masks[train].float().mean(dim=(1, 2)).sum())
    return cover * per_view, per_view


def default_image_scale(height: int, width: int, device: torch.device, preset: Preset | str = Preset.BALANCED) -> float:
    """The plan's image scale for images of ``height`` x ``width`` px on ``device``: the longest side
    capped at the preset's ``max_side`` (:mod:`wtopo.fitting.presets`; never upsampled)."""
    return min(1.0, _presets.budget(preset, device).max_side / max(height, width))


def iteration_budget(scene, device: torch.device, image_scale: float | None = None,
                     preset: Preset | str = Preset.BALANCED) -> tuple[int, int, str]:
    """``(warm-up, co-evolution, reason)``: the plan's iterations for ``scene`` on ``device`` when the
    configuration leaves them to it: the preset's base iterations (:mod:`wtopo.fitting.presets`); on CUDA
    with the means' decay horizon of ``_MEANS_DECAY_COEVO``, set by the plan beside them. The CPU's base
    covers up to ``_CPU_FIT_PIXELS`` training pixels to fit (mask pixels; every pixel without masks),
    proportionally more beyond while the warm-up renders at most ``_CPU_RENDER_PIXELS``. ``image_scale``:
    the trained scale (``None``: :func:`default_image_scale`). Any frame: only the images, masks and split
    count."""
    dev = "cuda" if device.type == "cuda" else "cpu"
    warm, coevo = _presets.budget(preset, device).iterations
    if dev == "cuda":
        return warm, coevo, "cuda budget"
    h, w = (int(x) for x in scene.images.shape[1:3])
    content, per_view = _fit_pixels(scene, default_image_scale(h, w, device, preset) if image_scale is None
                                    else image_scale)
    k = max(1.0, min(content / _CPU_FIT_PIXELS, _CPU_RENDER_PIXELS / (warm * per_view)))
    if k == 1.0:
        return warm, coevo, "cpu budget"
    return (int(round(warm * k)), int(round(coevo * k)),
            f"cpu budget x{k:.2f}: {content / 1e3:.0f}k training pixels to fit (> {_CPU_FIT_PIXELS // 1000}k), "
            f"at most {_CPU_RENDER_PIXELS / 1e6:.0f}M rendered pixels in the warm-up")


def _budget(plan: _Decisions, scene, cfg: FitConfig, device: torch.device, layout, image_scale: float) -> None:
    """Iterations, surfel cap and grids from the device, the region's size and the pixel footprint."""
    dev = "cuda" if device.type == "cuda" else "cpu"
    warm, coevo, why = iteration_budget(scene, device, image_scale, cfg.preset)
    plan.set("warmup_iterations", warm, why, cfg.warmup.iterations)
    plan.set("coevolution_iterations", coevo, why, cfg.coevolution.iterations)
    share = _MEANS_DECAY_COEVO[dev]  # of the co-evolution the plan settled on (a configured length moves it)
    warm_it, coevo_it = int(plan["warmup_iterations"]), int(plan["coevolution_iterations"])
    horizon = None if share is None else warm_it + round(share * coevo_it)
    interval = int(np.clip(warm_it // _DENSIFY_STEPS, *_DENSIFY_INTERVAL))
    plan.set("densify_interval", interval, f"{_DENSIFY_STEPS} density steps over the {warm_it}-iteration warm-up, "
             f"every {_DENSIFY_INTERVAL[0]}-{_DENSIFY_INTERVAL[1]} iterations", cfg.densify.interval)
    plan.set("means_decay_iterations", horizon,
             f"{dev} budget: the means' rate decays over the whole fit" if share is None else
             f"{dev} budget: the means' rate reaches its floor {share:g} of the way through the co-evolution and "
             f"keeps it for the rest", cfg.optim.means_decay_iterations)
    restart = _MEANS_RESTART[dev]
    plan.set("means_restart", restart,
             f"{dev} budget: the co-evolution's means restart at {restart:g} of optim.means and decay to their floor "
             f"at the fit's end" if restart > 0 else f"{dev} budget: the co-evolution's means keep the single decay",
             cfg.optim.means_restart)
    plan.set("max_surfels", _MAX_SURFELS[dev], f"{dev} budget", cfg.runtime.max_surfels)
    plan.set("filter_sigma", _FILTER_SIGMA[dev], f"{dev}: the renderer's screen-space low-pass, in pixels",
             cfg.filter_sigma)
    fp = _footprint(scene, layout, image_scale)
    ext = np.asarray(layout.roi_upper, dtype=np.float64) - np.asarray(layout.roi_lower, dtype=np.float64)
    side = float(np.max(ext))
    box = 2.0 * float(ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0]) / fp ** 2  # in footprint^2
    cap = _REINIT_FACES[dev]
    floor = min(_REINIT_MIN, cap)
    views = views_per_point(scene, layout)
    seen = min(1.0, views / _REINIT_VIEWS)
    rule = int(round(_REINIT_DENSITY * seen * box))
    faces = int(np.clip(rule, floor, cap))
    within = f"{cap} on {dev}" if floor == cap else f"within {floor}-{cap} on {dev}"
    plan.set("reinit_faces", faces,
             f"one surfel per face: {_REINIT_DENSITY:g} per squared pixel footprint of the region of interest's box "
             f"surface ({box:.0f} footprint^2; each surfel about a footprint across) times {seen:.2f} (its points "
             f"seen from {views:.1f} views, full density from {_REINIT_VIEWS:g}) gives {rule}, kept {within}",
             cfg.tsdf.max_faces)
    b = _presets.budget(cfg.preset, device)
    lo, hi = b.proxy_grid
    proxy = int(np.clip(16 * round(1.0 / (_PROXY_FOOTPRINTS * fp) / 16), lo, hi))  # Poisson spans the unit cube
    plan.set("proxy_resolution", proxy,
             f"pixel footprint {fp:.2e} at the region of interest; a cell of ~{_PROXY_FOOTPRINTS:g} footprints, "
             f"{lo}-{hi} on {dev}", cfg.mesh.resolution)
    lo, hi = b.final_grid
    final = int(np.clip(round(side / (_FINAL_FOOTPRINTS * fp)), lo, hi))
    plan.set("final_resolution", final,
             f"a voxel of {_FINAL_FOOTPRINTS:g} pixel footprints over the region of interest ({side:.3g} wide), "
             f"{lo}-{hi} on {dev} (twice as fine, up to {hi}, where the co-evolution finds thin parts)",
             cfg.final.resolution)
    reinit = min(int(plan.values["final_resolution"]), _REINIT_GRID_MAX)
    plan.set("reinit_resolution", reinit,
             f"the final mesh's voxel ({_FINAL_FOOTPRINTS:g} pixel footprints), at most {_REINIT_GRID_MAX} voxels: "
             "the re-initialisation keeps one surfel per face of at most the planned faces", cfg.tsdf.resolution)


def resolve_config(cfg: FitConfig, plan: Plan) -> FitConfig:
    """A copy of ``cfg`` with every decision of ``plan`` that has a configuration field written into it.

    A field the configuration set holds its value already (the plan took it over); a field left to the plan
    (``None``, ``AUTO``) gets the plan's. The fit reads the result and never the plan for these.
    """
    import copy

    out = copy.deepcopy(cfg)
    out.kind = SceneKind(plan.scene_kind)
    out.init.source = InitSource(plan.init_source)
    out.init.background_points = int(plan.background_points)
    out.losses.mask = float(plan.mask_loss)
    out.background = tuple(float(c) for c in plan.background)
    out.sh_degree = int(plan.sh_degree)
    out.losses.multiview = float(plan.multiview)
    out.densify.enabled = bool(plan.densify)
    out.densify.interval = int(plan.densify_interval)
    out.runtime.image_scale = float(plan.image_scale)
    out.warmup.iterations = int(plan.warmup_iterations)
    out.coevolution.iterations = int(plan.coevolution_iterations)
    horizon = plan.means_decay_iterations
    out.optim.means_decay_iterations = None if horizon is None else int(horizon)
    out.optim.means_restart = float(plan.means_restart)
    out.runtime.max_surfels = int(plan.max_surfels)
    out.filter_sigma = float(plan.filter_sigma)
    out.tsdf.max_faces = int(plan.reinit_faces)
    out.tsdf.resolution = int(plan.reinit_resolution)
    out.mesh.resolution = int(plan.proxy_resolution)
    out.final.resolution = int(plan.final_resolution)
    out.tsdf.enabled = bool(plan.tsdf_reinit)
    out.coevolution.enabled = bool(plan.mesh_loop)
    out.polish.iterations = int(plan.polish_iterations)
    out.mesh.level_sigma = float(plan.proxy_level_sigma)
    out.mesh.clip_to_region = bool(plan.proxy_clip)
    return out
