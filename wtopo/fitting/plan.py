# SPDX-License-Identifier: Apache-2.0
"""The stage plan: which parts of the fit a scene needs, each decision with its reason.

The plan is decided from the scene (masks, background, texture, view count, image size, device)
and the configuration; a configuration field that is set (not ``None``) overrides the plan's
choice and the plan says so. It is printed at the start of :func:`wtopo.fit` and stored in
``FitResult.plan`` and ``plan.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .config import FitConfig

__all__ = ["Decision", "Plan", "make_plan"]

_TEXTURE_STD = 0.02  # colour std (in [0,1] units) below which the foreground counts as untextured
_VIEW_CONSISTENCY = 0.04  # mean reprojected colour difference below which the scene counts as diffuse
_MIN_SH_VIEWS = 20  # fewer views than this cannot constrain view-dependent colour
_CPU_MAX_SIDE = 256  # longest image side trained on a CPU (keeps the default fit within minutes)
_GPU_MAX_SIDE = 1024
_MIN_EVAL_VIEWS = 12
_MASK_WEIGHT = 0.2  # alpha-vs-mask BCE weight: 0.5 pulls the surface in, 0 leaves short fits semi-transparent
# (benchmarks/fit.md)


@dataclass
class Decision:
    """One plan decision: the value, why, and whether the configuration overrode it."""

    value: object
    reason: str
    overridden: bool = False

    def to_dict(self) -> dict:
        v = self.value
        if isinstance(v, tuple):
            v = list(v)
        return {"value": v, "reason": self.reason, "overridden": self.overridden}


@dataclass
class Plan:
    """Ordered decisions (name -> :class:`Decision`)."""

    decisions: dict[str, Decision] = field(default_factory=dict)

    def __getitem__(self, name: str):
        return self.decisions[name].value

    def set(self, name: str, value, reason: str, override=None) -> None:
        """Record a decision; a non-``None`` ``override`` replaces ``value``."""
        if override is not None:
            self.decisions[name] = Decision(override, f"set in the configuration (plan: {value!r}, {reason})", True)
        else:
            self.decisions[name] = Decision(value, reason)

    def to_dict(self) -> dict:
        return {k: d.to_dict() for k, d in self.decisions.items()}

    def __str__(self) -> str:
        width = max((len(k) for k in self.decisions), default=0)
        lines = ["wtopo fit plan:"]
        for k, d in self.decisions.items():
            lines.append(f"  {k:<{width}}  {d.value!r:<14} {d.reason}")
        return "\n".join(lines)


def _as_np(x):
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _texture_std(images: np.ndarray, masks: np.ndarray | None) -> float:
    step = max(1, images.shape[0] // 8)
    imgs = images[::step].astype(np.float32)
    if masks is not None:
        m = masks[::step].astype(bool)
        px = imgs[m]
    else:
        px = imgs.reshape(-1, 3)
    if px.shape[0] < 2:
        return 0.0
    return float(px.std(axis=0).mean())


def _view_inconsistency(scene, images: np.ndarray, depths: np.ndarray, rng: np.random.Generator) -> float:
    """Mean colour difference of pixels reprojected between neighbouring views via the depth maps."""
    cams = scene.cameras
    n = len(cams)
    centers = np.stack([c.center for c in cams])
    diffs = []
    for a in rng.choice(n, size=min(n, 6), replace=False):
        d = np.linalg.norm(centers - centers[a], axis=1)
        d[a] = np.inf
        b = int(np.argmin(d))
        dep = depths[a]
        ii, jj = np.nonzero(dep > 0)
        if ii.size == 0:
            continue
        pick = rng.choice(ii.size, size=min(ii.size, 2000), replace=False)
        ii, jj = ii[pick], jj[pick]
        dirs = cams[a].pixel_directions_camera()[ii, jj]
        pc = dirs * dep[ii, jj][:, None]
        pw = (pc - cams[a].t) @ cams[a].R  # camera -> world
        uv, z = cams[b].project(pw)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cams[b].width) & (v < cams[b].height)
        if not ok.any():
            continue
        # visible in b: the reprojected depth matches b's depth map
        zb = depths[b][v[ok], u[ok]]
        vis = np.abs(zb - z[ok]) < 0.01 * np.abs(z[ok]).mean()
        if vis.sum() < 10:
            continue
        ca = images[a][ii[ok][vis], jj[ok][vis]]
        cb = images[b][v[ok][vis], u[ok][vis]]
        diffs.append(np.abs(ca - cb).mean())
    return float(np.mean(diffs)) if diffs else float("nan")


def make_plan(scene, cfg: FitConfig, device: torch.device) -> Plan:
    """Decide the stage plan for ``scene`` (in the internal frame) under ``cfg`` on ``device``."""
    plan = Plan()
    rng = np.random.default_rng(cfg.runtime.seed)
    images = _as_np(scene.images)
    masks = _as_np(getattr(scene, "masks", None))
    depths = _as_np(getattr(scene, "depths", None))
    points = getattr(scene, "points", None)
    n_views = len(scene.cameras)
    has_masks = masks is not None
    bg = getattr(scene, "background", None)

    plan.set("device", str(device), "CUDA available" if device.type == "cuda" else
             ("CPU requested" if cfg.runtime.device == "cpu" else "no CUDA device"))

    # -- initialisation
    n_pts = 0 if points is None else len(points)
    src = "points" if n_pts >= 100 else "cameras"
    why = (f"the scene has {n_pts} points" if src == "points"
           else f"the scene has {n_pts} points (< 100): random points in the cameras' common volume")
    plan.set("init_source", src, why, None if cfg.init.source == "auto" else cfg.init.source)

    # -- masks and background
    plan.set("mask_loss", _MASK_WEIGHT if has_masks else 0.0,
             "object masks given: alpha supervised by the mask" if has_masks
             else "no masks",
             cfg.losses.mask)
    plan.set("background_rule", not has_masks,
             "masked object: nothing behind it to keep" if has_masks
             else "no masks: background surfels far from the TSDF mesh keep their warm-up parameters")
    if bg is not None:
        bg_val, why = tuple(float(c) for c in bg), "the scene's background colour"
    else:
        bg_val, why = (0.0, 0.0, 0.0), "no background given: black"
    plan.set("background", bg_val, why, None if cfg.background is None else tuple(cfg.background))

    # -- colour model
    tex = _texture_std(images, masks)
    if tex < _TEXTURE_STD:
        deg, why = 0, f"untextured (foreground colour std {tex:.3f} < {_TEXTURE_STD})"
    elif n_views < _MIN_SH_VIEWS:
        deg, why = 0, f"{n_views} views (< {_MIN_SH_VIEWS}) cannot constrain view-dependent colour"
    elif depths is not None:
        inc = _view_inconsistency(scene, images, depths, rng)
        if np.isfinite(inc) and inc < _VIEW_CONSISTENCY:
            deg, why = 0, f"diffuse: reprojected colours differ by {inc:.3f} (< {_VIEW_CONSISTENCY}) between views"
        else:
            deg, why = 1, f"view-dependent colour: reprojected colours differ by {inc:.3f}"
    else:
        deg, why = 1, f"textured (colour std {tex:.3f}) and no depth to test view dependence"
    plan.set("sh_degree", deg, why, cfg.sh_degree)

    # -- density control
    dens = src == "cameras" or n_pts < 2000
    plan.set("densify", dens,
             "sparse initialisation: clone/split while coverage gaps exist" if dens
             else f"{n_pts} initial points: clone/split only while coverage gaps exist",
             cfg.densify.enabled)

    # -- image size
    h, w = images.shape[1:3]
    cap = _GPU_MAX_SIDE if device.type == "cuda" else _CPU_MAX_SIDE
    scale = min(1.0, cap / max(h, w))
    plan.set("image_scale", scale, f"{w}x{h} images; longest side capped at {cap} px on {device.type}",
             None if cfg.runtime.image_scale == 1.0 else cfg.runtime.image_scale)

    # -- held-out views
    test = getattr(scene, "test_indices", None)
    if test is not None and len(test):
        plan.set("eval_views", len(test), f"the scene's {len(test)} held-out views")
    else:
        n_eval = cfg.runtime.eval_views if n_views >= _MIN_EVAL_VIEWS else 0
        plan.set("eval_views", n_eval,
                 f"{n_views} views: {n_eval} held out for PSNR" if n_eval else
                 f"only {n_views} views: all used for training, PSNR on training views")

    # -- stages
    plan.set("tsdf_reinit", cfg.tsdf.enabled, "configuration" if not cfg.tsdf.enabled else
             "re-initialise from fused surfel depth between warm-up and co-evolution")
    plan.set("mesh_loop", cfg.coevolution.enabled and cfg.coevolution.iterations > 0,
             "proxy mesh rebuilt and supervising the surfels" if cfg.coevolution.enabled
             else "disabled in the configuration")
    plan.set("gt_metrics", getattr(scene, "gt_mesh", None) is not None and cfg.runtime.eval_metrics,
             "ground-truth mesh given: Chamfer / F-score at evaluations" if getattr(scene, "gt_mesh", None)
             is not None else "no ground-truth mesh")
    return plan
