# SPDX-License-Identifier: Apache-2.0
"""The fit loop: warm-up, TSDF re-initialisation, co-evolution with the proxy mesh, final mesh.

:class:`FitRun` owns the state of one fit (surfels, optimiser, iteration, history, timers) and
everything that makes it survivable: the non-finite guard (skip the step, restore the last good
state, abort with a checkpoint after too many failures in a row), checkpoints on an iteration and
a wall-clock cadence, resume from the newest valid checkpoint, and SIGINT / SIGTERM handling that
finishes the current step, checkpoints and returns the results so far.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import threading
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import trimesh

from .._profile import section
from . import densify as dens
from .checkpoint import CheckpointError, list_checkpoints, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from .config import FitConfig, NormalFlip, config_hash
from .evaluate import geometry_metrics
from .init import initial_surfels
from .losses import (
    boundary_band,
    depth_normals,
    distortion,
    mask_loss,
    mesh_depth_loss,
    mesh_normal_loss,
    normal_consistency,
    photometric,
    scale_regularizer,
)
from .plan import Plan, make_plan, resolve_config
from .proxy import ProxyMesh, ProxyResult, poisson_mesh
from .surfels import Surfels
from .tsdf import TSDFEmptyError, auto_bounds, cleanup_mesh, fuse_depths, hybrid_keep, mesh_to_surfels

__all__ = ["FitRun", "FitAborted", "STAGES"]

STAGES = ("warmup", "tsdf", "coevolution", "final")
_SNAPSHOT_EVERY = 25  # iterations between in-memory "last good" snapshots
_ALPHA_COVERED = 0.5  # a pixel is covered by the surfels when their opacity reaches this
_GAP_EMA = 0.9  # smoothing of the running uncovered-pixel fraction
_GAP_THRESHOLD = 0.002  # clone/split runs while more than this fraction of object pixels is uncovered
_DEPTH_EPS = 1e-4  # log-depth clamp, internal units (1e-4 of the unit cube)
_REINIT_OPACITY = 0.8  # TSDF re-initialised surfels start nearly opaque: they sit on the fused surface
_REMESH_SAMPLES = 200_000  # surface samples for the watertight Poisson re-mesh of the final mesh
# warm-up iterations an opacity reset needs after it; later resets are skipped (a reset 20 iterations
# before the TSDF re-initialisation left an 80-iteration fit at 15 % Chamfer, 0.78 % without it)
_RESET_RECOVERY = 100


class FitAborted(RuntimeError):
    """Too many consecutive non-finite steps; a checkpoint of the last good state was written."""


class _Timers:
    """Self time per named section (``wtopo._profile``): sections nested in a timed block, such as
    ``"scatter"`` inside ``"poisson"`` or ``"bvh_build"`` inside ``"raycast"``, are subtracted from it."""

    def __init__(self):
        self.total: dict[str, float] = defaultdict(float)

    def _add(self, name: str, seconds: float) -> None:
        self.total[name] += seconds

    def __call__(self, name: str):
        return section(name, add=self._add)


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _lrs(cfg: FitConfig) -> dict[str, float]:
    o = cfg.optim
    return {"means": o.means, "quats": o.quats, "log_scales": o.scales, "opacity_logits": o.opacities,
            "sh_dc": o.sh_dc, "sh_rest": o.sh_rest}


class FitRun:
    """One fit of a scene. Use :func:`wtopo.fit`; this class is its engine.

    Args:
        scene: the user's :class:`wtopo.Scene` (world frame).
        cfg: configuration.
        out_dir: run directory (checkpoints, outputs) or ``None``.
        progress: tqdm progress bars and the printed plan.
    """

    def __init__(self, scene, cfg: FitConfig, out_dir: str | Path | None, progress: bool):
        self.cfg = cfg
        self.progress = progress and cfg.runtime.progress
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.device = _resolve_device(cfg.runtime.device)
        self.timers = _Timers()
        self.t_start = time.perf_counter()
        self.elapsed_before = 0.0
        self.sim = scene.normalization()
        internal = scene.normalized().to(self.device)
        self.plan: Plan = make_plan(internal, cfg, self.device)
        user_cfg, cfg = cfg, resolve_config(cfg, self.plan)  # fields left to the plan (None) filled in
        self.cfg = cfg
        scale = float(self.plan["image_scale"])
        if scale < 1.0:
            internal = internal.downscaled(1.0 / scale)
        self.extent = float(1.0 - 2 * 0.1)  # the region of interest spans [0.1, 0.9]^3 (normalization margin)
        self._split(internal)
        self.gt = internal.gt_mesh
        self.hash = config_hash(user_cfg)
        self.gen = torch.Generator().manual_seed(cfg.runtime.seed)
        self.bg = torch.tensor(self.plan["background"], dtype=torch.float32, device=self.device)
        from ..rasterize import RasterConfig

        self.raster = RasterConfig(filter_sigma=cfg.filter_sigma)
        self._bands: dict[int, torch.Tensor] = {}  # training view -> silhouette band (masks are fixed)
        self.it = 0
        self.tsdf_done = False
        self.history: list[dict] = []
        self.events: list[dict] = []
        self.failures = 0
        self.total_failures = 0
        self.gap = 1.0
        self.loss_sums: dict[str, float] = defaultdict(float)
        self.loss_count = 0
        self.loss_ema = 0.0
        self.proxy: ProxyMesh = ProxyMesh(cfg.mesh)
        self.proxy_mesh: ProxyResult | None = None
        self.tsdf_info: dict = {}
        self.status = "running"
        self.surfels: Surfels | None = None
        self.opt: torch.optim.Adam | None = None
        self._good = None
        self._stop = False
        self._last_ckpt_time = time.perf_counter()
        self.timeline = None

    # -- data ------------------------------------------------------------------------------------
    def _split(self, sc) -> None:
        n = len(sc.cameras)
        if sc.test_indices is not None and len(sc.test_indices):
            test = [int(i) for i in sc.test_indices]
            train = [int(i) for i in (sc.train_indices if sc.train_indices is not None else range(n)) if i not in test]
        elif self.plan["eval_views"]:
            k = int(self.plan["eval_views"])
            test = sorted({int(round(x)) for x in np.linspace(0, n - 1, k + 2)[1:-1]})
            train = [i for i in range(n) if i not in test]
        else:
            test, train = [], list(range(n))
        self.train = sc.subset(train)
        self.test = sc.subset(test) if test else sc.subset(train[:: max(1, len(train) // 4)])

    @property
    def warmup_end(self) -> int:
        return int(self.cfg.warmup.iterations)

    @property
    def total_iterations(self) -> int:
        return self.warmup_end + int(self.cfg.coevolution.iterations)

    def elapsed(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.t_start

    def _view(self, it: int) -> int:
        n = len(self.train.cameras)
        epoch, k = divmod(it, n)
        g = torch.Generator().manual_seed(self.cfg.runtime.seed * 1_000_003 + epoch)
        return int(torch.randperm(n, generator=g)[k])

    # -- optimiser ---------------------------------------------------------------------------------
    def _set_surfels(self, surfels: Surfels, opt_state: dict | None = None) -> None:
        self.surfels = surfels
        self.opt = surfels.optimizer(_lrs(self.cfg))
        if opt_state is not None:
            self.opt.load_state_dict(opt_state)
        self._snapshot()

    def _snapshot(self) -> None:
        self._good = (self.surfels.state_dict(), self.opt.state_dict())

    def _restore(self) -> None:
        sd, od = self._good
        self.surfels = Surfels.from_state_dict(sd, self.device)
        self.opt = self.surfels.optimizer(_lrs(self.cfg))
        self.opt.load_state_dict(od)

    def _update_lr(self) -> None:
        o = self.cfg.optim
        frac = min(1.0, self.it / max(1, self.total_iterations))
        lr = o.means * (o.means_final / o.means) ** frac if o.means > 0 and o.means_final > 0 else o.means
        for g in self.opt.param_groups:
            if g["name"] == "means":
                g["lr"] = lr

    # -- rendering -------------------------------------------------------------------------------------
    def _render(self, camera):
        from ..rasterize import rasterize_surfels

        s = self.surfels
        return rasterize_surfels(s.means, s.quats, s.scales, s.opacities, s.sh, camera, sh_degree=s.sh_degree,
                                 background=self.bg, config=self.raster)

    def _render_depths(self, cameras, which: str):
        depths, colors = [], []
        with torch.no_grad():
            for cam in cameras:
                out = self._render(cam)
                d = out.median_depth if which == "median" else out.depth
                d = torch.where(out.alpha >= self.cfg.tsdf.alpha_threshold, d, torch.zeros_like(d))
                depths.append(d.detach().cpu().numpy())
                colors.append(out.rgb.detach().clamp(0, 1).cpu().numpy())
        return depths, colors

    # -- one iteration -------------------------------------------------------------------------------------
    def _losses(self, stage: str, vi: int) -> tuple[dict[str, torch.Tensor], object]:
        cfg, lc, s, T = self.cfg, self.cfg.losses, self.surfels, self.timers
        cam = self.train.cameras[vi]
        img = self.train.images[vi]
        with T("render"):
            out = self._render(cam)
        L: dict[str, torch.Tensor] = {}
        with T("losses"):
            band = None
            if self.train.masks is not None and lc.silhouette_band > 0:
                band = self._bands.get(vi)
                if band is None:
                    band = self._bands[vi] = boundary_band(self.train.masks[vi], lc.silhouette_band)
            # the band is left out by rendering the target there: zero loss, zero gradient
            rgb = out.rgb if band is None else torch.where(band[..., None], img, out.rgb)
            L["photo"] = photometric(rgb, img, lc.dssim)
            alpha_d = out.alpha.detach()
            covered = alpha_d >= _ALPHA_COVERED
            if self.train.masks is not None:
                m = self.train.masks[vi]
                if float(self.plan["mask_loss"]) > 0:
                    a = out.alpha if band is None else torch.where(band, m.to(out.alpha.dtype), out.alpha)
                    L["mask"] = float(self.plan["mask_loss"]) * mask_loss(a, m)
                gap = float((m & ~covered).sum()) / max(1.0, float(m.sum()))
            else:
                gap = float((~covered).float().mean())
            self.gap = _GAP_EMA * self.gap + (1 - _GAP_EMA) * gap
            late = stage != "warmup"
            if lc.normal > 0 and (late or self.it >= lc.normal_start):
                o, d = cam.pixel_rays(self.device)
                dn, dmask = depth_normals(out.median_depth, o, d, covered)
                L["normal"] = lc.normal * normal_consistency(out.normal, dn, out.alpha, dmask)
            if lc.distortion > 0 and (late or self.it >= lc.distortion_start):
                L["distortion"] = lc.distortion * distortion(out.distortion)
            if lc.scale > 0:
                L["scale"] = lc.scale * scale_regularizer(s.scales, lc.max_anisotropy)
        co = self.cfg.coevolution
        if (stage == "coevolution" and co.enabled and (lc.mesh_depth > 0 or lc.mesh_normal > 0)
                and (self.it - self.warmup_end) % max(1, co.mesh_every) == 0):
            with T("proxy"):
                pm = self.proxy.build(s)
            self.proxy_mesh = pm
            if pm is not None:
                with T("raycast"):
                    mr = self.proxy.render(pm, cam)
                with T("losses"):
                    both = mr.mask & covered
                    if lc.mesh_depth > 0:
                        sd = out.median_depth if lc.mesh_depth_source == "median" else out.depth
                        L["mesh_depth"] = lc.mesh_depth * mesh_depth_loss(
                            sd, mr.depth, both, eps=_DEPTH_EPS, form=str(getattr(lc.depth_form, "value", lc.depth_form)),
                            extent=self.extent)
                    if lc.mesh_normal > 0:
                        L["mesh_normal"] = lc.mesh_normal * mesh_normal_loss(out.normal, mr.normal, both)
        return L, out

    def _failure(self, why: str, terms: dict[str, float]) -> None:
        self.failures += 1
        self.total_failures += 1
        self.events.append({"iteration": self.it, "event": "non_finite", "why": why, "terms": terms})
        self.opt.zero_grad(set_to_none=True)
        self._restore()
        if self.failures >= self.cfg.runtime.max_consecutive_failures:
            self.status = "aborted"
            path = self._checkpoint(force=True)
            raise FitAborted(f"{self.failures} consecutive non-finite steps at iteration {self.it} ({why}); "
                             f"last good state checkpointed to {path}")

    def _step(self, stage: str) -> None:
        vi = self._view(self.it)
        L, out = self._losses(stage, vi)
        total = sum(L.values())
        terms = {k: float(v.detach()) for k, v in L.items()}  # host sync: one per iteration
        if not math.isfinite(sum(terms.values())):
            self._failure("loss", {k: v for k, v in terms.items() if not math.isfinite(v)})
            return
        with self.timers("backward"):
            total.backward()
        bad = [k for k, p in self.surfels.params.items() if p.grad is not None and not bool(torch.isfinite(p.grad).all())]
        if bad:
            self._failure("gradient", {k: float("nan") for k in bad})
            return
        with self.timers("optimizer"):
            self._update_lr()
            self.opt.step()
        if not self.surfels.is_finite():
            self._failure("parameters", {})
            return
        s = self.surfels
        with torch.no_grad():
            visible = out.visibility > 0
            if stage == "warmup" and out.means2d.grad is not None:
                cam = self.train.cameras[vi]
                dens.accumulate_gradients(s, out.means2d.grad, visible, cam.width, cam.height)
            center = torch.as_tensor(self.train.cameras[vi].center, dtype=torch.float32, device=self.device)
            dens.accumulate_view_directions(s, center, visible)
        self.opt.zero_grad(set_to_none=True)
        self.failures = 0
        for k, v in terms.items():
            self.loss_sums[k] += v
        self.loss_sums["total"] += sum(terms.values())
        self.loss_ema = sum(terms.values()) if self.loss_count == 0 and not self.history else (
            0.9 * self.loss_ema + 0.1 * sum(terms.values()))
        self.loss_count += 1
        if self.it % _SNAPSHOT_EVERY == 0:
            self._snapshot()

    # -- density control --------------------------------------------------------------------------------------
    def _warmup_density(self) -> None:
        dc, it, W = self.cfg.densify, self.it, self.warmup_end
        if it < dc.start or it % max(1, dc.interval) != 0:
            return
        changed = False
        with self.timers("densify"):
            if self.plan["densify"] and it < dc.stop_fraction * W:
                if self.gap > _GAP_THRESHOLD:
                    c, sp = dens.clone_and_split(self.surfels, dc, self.extent, self.cfg.runtime.max_surfels, self.gen)
                    self.events.append({"iteration": it, "event": "densify", "cloned": c, "split": sp,
                                        "gap": self.gap})
                    changed = True
                else:
                    self.events.append({"iteration": it, "event": "densify_skipped", "gap": self.gap})
                    self.surfels.buffers["grad_accum"].zero_()
                    self.surfels.buffers["grad_count"].zero_()
            removed = dens.prune_by_opacity(self.surfels, dc.prune_opacity)
            changed |= removed > 0
            if dc.opacity_reset_interval and it % dc.opacity_reset_interval == 0 and it < dc.stop_fraction * W:
                if W - it >= _RESET_RECOVERY:
                    dens.reset_opacity(self.surfels, dc.opacity_reset_value)
                    changed = True
                else:  # too late: the surfels would reach the TSDF re-initialisation still transparent
                    self.events.append({"iteration": it, "event": "opacity_reset_skipped",
                                        "remaining_warmup": W - it})
        if changed:
            self._snapshot()

    def _mesh_guidance(self) -> None:
        """Normal signs, geometry-aware prune and densification against the current proxy mesh.

        The proxy is rebuilt here from the current surfels (not reused from the last step), so a
        resumed run makes the same decisions as an uninterrupted one.
        """
        co, dc, mc = self.cfg.coevolution, self.cfg.densify, self.cfg.mesh
        k = self.it - self.warmup_end
        if k % max(1, co.correspondence_every) != 0:
            return
        with self.timers("guidance"):
            s = self.surfels
            info = {"iteration": self.it, "event": "mesh_guidance"}
            pm = None
            if co.enabled:
                with torch.no_grad():
                    pm = self.proxy.build(s)
            if pm is None:
                mode = NormalFlip.VIEW if NormalFlip(mc.normal_flip) == NormalFlip.MESH else NormalFlip(mc.normal_flip)
                info["signs"] = dens.align_normal_signs(s, mode, generator=self.gen)
                self.events.append(info)
                self._snapshot()
                return
            verts, faces = pm.verts.detach(), pm.faces
            fid, dist, _ = self.proxy.closest(pm, s.means)
            fn, _ = dens.face_normals(verts, faces)
            mn = torch.where((fid >= 0)[:, None], fn[fid.clamp_min(0).long()], torch.zeros_like(s.means.detach()))
            info["signs"] = dens.align_normal_signs(s, NormalFlip(mc.normal_flip), mesh_normal=mn, distance=dist,
                                                    max_distance=mc.flip_distance * self.extent, generator=self.gen)
            if dc.geometry_densify:
                info["spawned"] = dens.geometry_densify(s, verts, faces, fid, max_new=dc.geometry_densify_max,
                                                        max_surfels=self.cfg.runtime.max_surfels, generator=self.gen)
                dist = torch.cat([dist, torch.zeros(len(s) - dist.shape[0], dtype=dist.dtype, device=dist.device)])
            if dc.geometry_prune:
                info["pruned"] = dens.geometry_prune(s, dist, max_distance=dc.geometry_prune_distance * self.extent,
                                                     max_opacity=dc.geometry_prune_opacity)
            self.events.append(info)
        self._snapshot()

    # -- stages -------------------------------------------------------------------------------------------
    def _bar(self, stage: str, start: int, end: int):
        if not self.progress:
            return None
        from tqdm.auto import tqdm

        return tqdm(total=end - start, initial=max(0, min(self.it, end) - start), desc=stage, dynamic_ncols=True,
                    leave=True)

    def _iterate(self, stage: str, start: int, end: int) -> None:
        bar = self._bar(stage, start, end)
        try:
            while self.it < end and not self._stop:
                if stage != "warmup":
                    self._mesh_guidance()  # before the step: signs are set before the first proxy build
                self._step(stage)
                if stage == "warmup":
                    self._warmup_density()
                self.it += 1
                if self.timeline is not None and self.cfg.runtime.usd_every and self.it % self.cfg.runtime.usd_every == 0:
                    self._timeline_sample()
                if self.cfg.runtime.eval_every and self.it % self.cfg.runtime.eval_every == 0:
                    self._evaluate(stage)
                self._maybe_checkpoint()
                if self.cfg.runtime.stop_at is not None and self.it >= self.cfg.runtime.stop_at:
                    self._stop = True
                if bar is not None:
                    bar.update(1)
                    if self.it % 10 == 0 or self.it == end:
                        bar.set_postfix(loss=f"{self.loss_ema:.4f}", surfels=len(self.surfels),
                                        faces=0 if self.proxy_mesh is None else self.proxy_mesh.num_faces,
                                        elapsed=f"{self.elapsed():.0f}s", refresh=False)
        finally:
            if bar is not None:
                bar.close()

    def _tsdf_reinit(self) -> None:
        tc = self.cfg.tsdf
        with self.timers("tsdf"):
            cams = self.train.cameras[:: max(1, math.ceil(len(self.train.cameras) / tc.max_views))]
            depths, colors = self._render_depths(cams, tc.depth)
            s = self.surfels
            bounds = auto_bounds(s.means, s.opacities, resolution=tc.resolution, truncation_voxels=tc.truncation_voxels)
            self.tsdf_info = {"reinit_bounds": bounds.to_dict()}
            try:
                mesh = fuse_depths(cams, depths, colors, bounds)
            except TSDFEmptyError as e:
                warnings.warn(f"TSDF re-initialisation skipped, keeping the warm-up surfels: {e}", RuntimeWarning,
                              stacklevel=2)
                self.events.append({"iteration": self.it, "event": "tsdf_empty", "why": str(e)})
                self.tsdf_done = True
                return
            mesh = cleanup_mesh(mesh, largest_component=not self.plan["background_rule"])
            new = mesh_to_surfels(mesh, max_faces=tc.max_faces, device=self.device, sh_degree=s.sh_degree,
                                  opacity=_REINIT_OPACITY)
            kept = 0
            if self.plan["background_rule"]:
                from ..raycast import closest_faces

                v = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=self.device)
                f = torch.as_tensor(mesh.faces, dtype=torch.int32, device=self.device)
                _, dist, _ = closest_faces(v, f, s.means.detach())
                p, b = hybrid_keep(s, dist, tc.hybrid_distance * self.extent)
                kept = int(p["means"].shape[0])
                new.append(p, b)
            if self.cfg.mesh.poisson_box == "initial_mesh" or self.cfg.mesh.surface_prior > 0:
                pts, fi = trimesh.sample.sample_surface(mesh, 20000, seed=self.cfg.runtime.seed)
                prior = (torch.as_tensor(pts, dtype=torch.float32, device=self.device),
                         torch.as_tensor(mesh.face_normals[fi], dtype=torch.float32, device=self.device))
                box = mesh.bounds if self.cfg.mesh.poisson_box == "initial_mesh" else None
                self.proxy = ProxyMesh(self.cfg.mesh, box=box, prior=prior)
                self.tsdf_info["poisson_box"] = None if box is None else np.asarray(box).tolist()
            self.tsdf_info.update({"reinit_faces": int(len(mesh.faces)), "reinit_surfels": len(new) - kept,
                                   "hybrid_kept": kept})
            self.events.append({"iteration": self.it, "event": "tsdf_reinit", **self.tsdf_info})
            self._set_surfels(new)
        self.tsdf_done = True

    def final_mesh(self) -> trimesh.Trimesh:
        """The returned mesh in the internal frame (TSDF of rendered depth, or the proxy)."""
        fc = self.cfg.final
        with self.timers("final"):
            mesh = None
            if fc.method == "tsdf":
                depths, colors = self._render_depths(self.train.cameras, self.cfg.tsdf.depth)
                bounds = auto_bounds(self.surfels.means, self.surfels.opacities, resolution=fc.resolution,
                                     truncation_voxels=self.cfg.tsdf.truncation_voxels)
                self.tsdf_info["final_bounds"] = bounds.to_dict()
                try:
                    mesh = fuse_depths(self.train.cameras, depths, colors, bounds)
                except TSDFEmptyError as e:
                    warnings.warn(f"final TSDF empty, returning the proxy mesh: {e}", RuntimeWarning, stacklevel=2)
                    self.events.append({"iteration": self.it, "event": "final_tsdf_empty", "why": str(e)})
            elif fc.method != "proxy":
                raise ValueError(f"final.method must be 'tsdf' or 'proxy', got {fc.method!r}")
            if mesh is None:
                if NormalFlip(self.cfg.mesh.normal_flip) != NormalFlip.RANDOM and not (
                        self.cfg.coevolution.enabled and self.it > self.warmup_end):
                    # no mesh guidance ran: orient the normals by the cameras that saw each surfel
                    dens.align_normal_signs(self.surfels, NormalFlip.VIEW)
                final = ProxyMesh(dataclasses.replace(self.cfg.mesh, resolution=fc.poisson_resolution),
                                  box=self.proxy.box, prior=self.proxy.prior)
                with torch.no_grad():
                    pm = final.build(self.surfels)
                if pm is None:
                    raise TSDFEmptyError("no final mesh: the TSDF fusion and the proxy mesh are both empty")
                mesh = trimesh.Trimesh(pm.verts.detach().cpu().numpy(), pm.faces.cpu().numpy(), process=True)
            mesh = cleanup_mesh(mesh, largest_component=fc.largest_component)
            if fc.watertight and not mesh.is_watertight:
                mesh = self._poisson_remesh(mesh)
        return mesh

    def _poisson_remesh(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """A closed mesh through ``mesh``: Poisson of its area samples (zero level set is closed)."""
        pts, fi = trimesh.sample.sample_surface(mesh, _REMESH_SAMPLES, seed=self.cfg.runtime.seed)
        lo, hi = mesh.bounds
        side = float(np.max(hi - lo)) * 1.1
        lower = 0.5 * (lo + hi) - 0.5 * side
        p = torch.as_tensor((pts - lower) / side, dtype=torch.float32)
        n = torch.as_tensor(mesh.face_normals[fi], dtype=torch.float32)
        w = torch.ones(p.shape[0])
        verts, faces = poisson_mesh(p, n, w, int(self.cfg.final.resolution), sigma=1.0, padding=self.cfg.mesh.padding)
        out = trimesh.Trimesh(verts.detach().cpu().numpy() * side + lower, faces.cpu().numpy(), process=True)
        out = cleanup_mesh(out, largest_component=self.cfg.final.largest_component)
        self.events.append({"iteration": self.it, "event": "poisson_remesh", "watertight": bool(out.is_watertight)})
        return out if len(out.faces) else mesh

    # -- evaluation ----------------------------------------------------------------------------------------------------
    def _psnr(self) -> float:
        from ..metrics import psnr

        vals = []
        with torch.no_grad():
            for cam, img in zip(self.test.cameras, self.test.images):
                vals.append(float(psnr(self._render(cam).rgb.clamp(0, 1), img)))
        return float(np.mean(vals))

    def _evaluate(self, stage: str, mesh: trimesh.Trimesh | None = None) -> dict:
        with self.timers("evaluate"):
            n = max(1, self.loss_count)
            rec = {"iteration": self.it, "stage": stage, "elapsed": round(self.elapsed(), 3),
                   "stage_times": {k: round(v, 3) for k, v in self.timers.total.items()},
                   "losses": {k: v / n for k, v in self.loss_sums.items()}, "surfels": len(self.surfels),
                   "proxy_faces": 0 if self.proxy_mesh is None else self.proxy_mesh.num_faces}
            self.loss_sums.clear()
            self.loss_count = 0
            if self.plan["gt_metrics"]:
                rec["psnr"] = self._psnr()
                target = mesh
                if target is None and self.proxy_mesh is not None:
                    target = (self.proxy_mesh.verts.detach().cpu(), self.proxy_mesh.faces.cpu())
                if target is not None:
                    g = geometry_metrics(target, self.gt, seed=self.cfg.runtime.seed)
                    if g:
                        rec.update({"chamfer": g["chamfer_rel"], "f_score": g["f_score"],
                                    "accuracy": g["accuracy_rel"], "completeness": g["completeness_rel"]})
        self.history.append(rec)
        return rec

    # -- checkpoints -----------------------------------------------------------------------------------------------
    def _ckpt_dir(self) -> Path | None:
        return None if self.out_dir is None else self.out_dir / "checkpoints"

    def _state(self) -> dict:
        return {
            "surfels": self._good[0] if self._good is not None else self.surfels.state_dict(),
            "optimizer": self._good[1] if self._good is not None else self.opt.state_dict(),
            "iteration": self.it, "tsdf_done": self.tsdf_done, "history": self.history, "events": self.events,
            "gap": self.gap, "loss_sums": dict(self.loss_sums), "loss_count": self.loss_count,
            "elapsed": self.elapsed(), "timers": dict(self.timers.total), "rng": rng_state(),
            "generator": self.gen.get_state(), "config_hash": self.hash, "config": self.cfg.to_dict(),
            "normalization": {"scale": self.sim.scale, "translation": list(self.sim.translation)},
            "proxy": {"box": None if self.proxy.box is None else [np.asarray(b).tolist() for b in self.proxy.box],
                      "prior": self.proxy.prior},
            "tsdf_info": self.tsdf_info, "total_failures": self.total_failures,
        }

    def _checkpoint(self, *, force: bool = False) -> Path | None:
        d = self._ckpt_dir()
        if d is None:
            return None
        if not force:
            self._snapshot()  # a scheduled checkpoint stores the current (finite) state
        with self.timers("checkpoint"):
            path = save_checkpoint(d, self.it, self._state(), keep=max(2, self.cfg.runtime.keep_checkpoints))
        self._last_ckpt_time = time.perf_counter()
        return path

    def _maybe_checkpoint(self) -> None:
        rt = self.cfg.runtime
        due = (rt.checkpoint_every and self.it % rt.checkpoint_every == 0) or (
            rt.checkpoint_seconds and time.perf_counter() - self._last_ckpt_time > rt.checkpoint_seconds)
        if due:
            self._checkpoint()

    def _resume(self) -> bool:
        d = self._ckpt_dir()
        if d is None or not list_checkpoints(d):
            return False
        try:
            st = load_checkpoint(d, config_hash=self.hash)
        except CheckpointError as e:
            raise ValueError(f"{self.out_dir} holds checkpoints this configuration cannot resume ({e}); "
                             "use another out_dir or the configuration of that run") from None
        self._set_surfels(Surfels.from_state_dict(st["surfels"], self.device), st["optimizer"])
        self.it = int(st["iteration"])
        self.tsdf_done = bool(st["tsdf_done"])
        self.history = list(st["history"])
        self.events = list(st["events"]) + [{"iteration": self.it, "event": "resumed", "from": st["path"]}]
        self.gap = float(st["gap"])
        self.loss_sums = defaultdict(float, st["loss_sums"])
        self.loss_count = int(st["loss_count"])
        self.elapsed_before = float(st["elapsed"])
        self.timers.total = defaultdict(float, st["timers"])
        self.total_failures = int(st["total_failures"])
        self.tsdf_info = dict(st["tsdf_info"])
        set_rng_state(st["rng"])
        self.gen.set_state(st["generator"])
        px = st["proxy"]
        self.proxy = ProxyMesh(self.cfg.mesh, box=None if px["box"] is None else tuple(np.asarray(b) for b in px["box"]),
                               prior=px["prior"])
        return True

    # -- timeline --------------------------------------------------------------------------------------------------
    def _open_timeline(self) -> None:
        if self.out_dir is None or not self.cfg.runtime.usd_every:
            return
        from ..io import TimelineWriter

        self.timeline = TimelineWriter(self.out_dir / "timeline.usdc")
        self.timeline.add_cameras([self.sim.to_world(c) for c in self.train.cameras])

    def _timeline_sample(self) -> None:
        s, sim = self.surfels, self.sim
        kw = {}
        if self.proxy_mesh is not None:
            kw = {"mesh_verts": sim.to_world(self.proxy_mesh.verts.detach().cpu().double().numpy()),
                  "mesh_faces": self.proxy_mesh.faces.cpu().numpy()}
        with self.timers("timeline"):
            self.timeline.add_sample(self.it, means=sim.to_world(s.means.detach().cpu().double().numpy()),
                                     quats=s.quats.detach().cpu().numpy(),
                                     scales=sim.length_to_world(s.scales.detach().cpu().double().numpy()),
                                     opacities=s.opacities.detach().cpu().numpy(), colors_or_sh=s.sh.detach().cpu().numpy(),
                                     **kw)

    # -- driver ----------------------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _signals(self):
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def handler(signum, frame):
            if self._stop:  # second signal: stop now
                raise KeyboardInterrupt
            self._stop = True
            self.events.append({"iteration": self.it, "event": "signal", "signal": int(signum)})

        old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for sig, h in old.items():
                signal.signal(sig, h)

    def run(self) -> trimesh.Trimesh:
        """Run (or resume) every stage; returns the final mesh in the internal frame."""
        with self._signals():
            resumed = self._resume()
            if not resumed:
                s = initial_surfels(self.train, self.cfg.init, self.plan["init_source"], sh_degree=int(self.plan["sh_degree"]),
                                    device=self.device, generator=self.gen)
                self._set_surfels(s)
            if self.progress:
                print(self.plan)
                if resumed:
                    print(f"resuming at iteration {self.it}")
            self._open_timeline()
            self._iterate("warmup", 0, self.warmup_end)
            if not self._stop and not self.tsdf_done and self.plan["tsdf_reinit"]:
                self._tsdf_reinit()
                self._evaluate("tsdf")
            if not self._stop and self.warmup_end < self.total_iterations and self.it >= self.warmup_end:
                self._iterate("coevolution", self.warmup_end, self.total_iterations)
            self.status = "interrupted" if self._stop else "completed"
            if self.it > 0 and self._ckpt_dir() is not None:
                self._checkpoint()
            mesh = self.final_mesh()
            self._evaluate("final", mesh=mesh)
            if self.timeline is not None:
                with self.timers("timeline"):
                    self.timeline.add_mesh("final", self.sim.to_world(np.asarray(mesh.vertices)), np.asarray(mesh.faces))
                    self.timeline.close()
        return mesh
