# SPDX-License-Identifier: Apache-2.0
"""Density control of the fit as one strategy object with per-iteration hooks (gsplat's ``Strategy``).

The driver calls, each iteration:

1. :meth:`DensityStrategy.step_pre_forward`: in co-evolution, mesh guidance against a proxy
   rebuilt from the current surfels (normal signs, geometry-aware densify and prune);
2. :meth:`DensityStrategy.step_pre_backward`: the running coverage gap of the rendered view;
3. :meth:`DensityStrategy.step_post_backward` after a finite optimiser step: screen-space
   gradient (warm-up) and view-direction accumulation;
4. :meth:`DensityStrategy.step_end`: in warm-up, clone / split where coverage gaps remain, prune
   transparent surfels and reset opacities early enough to recover before the TSDF stage.

Hooks that change the surfels return ``True`` so the driver snapshots the new last-good state.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import torch

from . import densify as dens
from .background import BackgroundState, prune_near_cameras
from .config import FitConfig, NormalFlip, stage_iteration
from .plan import _DENSIFY_INTERVAL
from .proxy import ProxyMesh
from .stages import ROI_EXTENT, Record, Stage
from .surfels import Surfels

__all__ = ["DensityStrategy", "StepInfo", "is_reset_step"]

_GAP_EMA = 0.9  # smoothing of the running uncovered-pixel fraction
_GAP_THRESHOLD = 0.002  # clone/split runs while more than this fraction of object pixels is uncovered
_OPACITY_RESET_VALUE = 0.1  # a reset clamps opacities to at most this (low, yet above the 0.05 prune threshold)
_GEOMETRY_DENSIFY_MAX = 2000  # surfels spawned per geometry-aware step at most: bounds the growth of one step
# warm-up iterations an opacity reset needs after it; later resets are skipped (a reset 20 iterations
# before the TSDF re-initialisation left an 80-iteration fit at 15 % Chamfer, 0.78 % without it)
_RESET_RECOVERY = 100
DENSIFY_START = 0.25  # density control starts this fraction of the way through the warm-up (stage_iteration)
DENSIFY_STOP = 0.8  # clone/split and opacity resets stop after this fraction of the warm-up (3DGS: half)
PRUNE_OPACITY = 0.05  # surfels less opaque than this are pruned at every density step (3DGS: 0.005)
_CORRESPONDENCE_FRACTION = 0.5  # mesh guidance refreshes every this fraction of the co-evolution
_SIGN_DISTANCE = 3.0  # mesh-guided signs: a proxy face nearer than this many in-plane sigmas of a surfel decides it
_GEOMETRY_PRUNE_DISTANCE = 0.02  # geometry-aware prune: "far from the proxy", fraction of the scene extent
_GEOMETRY_PRUNE_OPACITY = 0.3  # geometry-aware prune: "low opacity"


@dataclasses.dataclass
class StepInfo:
    """What one iteration tells the strategy.

    Attributes:
        stage: the running stage.
        render: the :class:`wtopo.rasterize` output of the training view (``means2d`` carries its gradient
            after the backward pass).
        covered: pixels [H, W] bool whose rendered opacity reaches the coverage threshold.
        mask: the view's object mask [H, W] bool, or ``None``.
        camera: the training camera (internal frame).
    """

    stage: Stage
    render: object
    covered: torch.Tensor
    mask: torch.Tensor | None
    camera: object


def is_reset_step(it: int, every: int, interval: int) -> bool:
    """Whether the density step ``it`` (a multiple of ``interval``) is the one nearest an intended opacity reset.

    Resets are meant every ``every`` iterations (``every``, ``2 * every``, ...), but density control runs only
    every ``interval``: an intended iteration ``t`` falls on the step ``interval * floor(t / interval + 1/2)``
    (halves to the later step, as :func:`~.config.stage_iteration` rounds), i.e. ``it`` takes every ``t`` in
    ``[it - interval / 2, it + interval / 2)``, so ``every`` need not be a multiple of ``interval`` (the CUDA
    budget's reset at 2,250 of a 3,000-iteration warm-up runs at the step of 2,300). Several intended resets in
    one window reset once.
    """
    k = max(1, -((interval - 2 * it) // (2 * every)))  # the first intended reset at or after the window's start
    return 2 * k * every < 2 * it + interval  # ... lies before its end


class DensityStrategy:
    """Warm-up density control and co-evolution mesh guidance.

    Args:
        cfg: configuration (``densify``, ``coevolution``, ``mesh``, ``runtime.max_surfels``).
        densify: the plan's decision whether clone / split runs at all.
        warmup_end: first iteration after the warm-up.
        generator: the fit's torch generator (split samples, random signs, new surfels).
        record: event sink.
        timers: the fit's section timers (``"densify"``, ``"guidance"``).

    Attributes:
        gap: running average of the uncovered fraction of object pixels (all pixels without masks).

    Limitations:
        Mesh guidance rebuilds the proxy from the current surfels rather than reusing the last
        step's, so that a resumed run makes the same decisions as an uninterrupted one.
    """

    def __init__(self, cfg: FitConfig, *, densify: bool, warmup_end: int, generator: torch.Generator,
                 record: Record, timers: Callable, background: BackgroundState | None = None):
        self.cfg = cfg
        self.densify = densify
        self.warmup_end = warmup_end
        self.gen = generator
        self.record = record
        self.timers = timers
        self.gap = 1.0
        self.background = background
        """Scenes: the region of interest and cameras; background surfels are spared by the
        geometry-aware prune, surfels on a lens are pruned at every density step, and clone/split
        runs by gradient alone (the background leaves no coverage gap to wait for)."""

    # -- hooks ----------------------------------------------------------------------------------------
    def step_pre_forward(self, stage: Stage, it: int, surfels: Surfels, proxy: ProxyMesh) -> bool:
        """Mesh guidance every :data:`_CORRESPONDENCE_FRACTION` of the co-evolution, before the step (the
        signs are set before the first proxy build). Returns whether it ran."""
        co = self.cfg.coevolution
        every = max(1, stage_iteration(_CORRESPONDENCE_FRACTION, co.iterations))
        if stage != Stage.COEVOLUTION or (it - self.warmup_end) % every != 0:
            return False
        with self.timers("guidance"):
            self._mesh_guidance(surfels, proxy)
        return True

    @staticmethod
    def coverage_counts(info: StepInfo) -> torch.Tensor:
        """What :meth:`step_pre_backward` needs from the rendered view, float64 [2] on the device.

        Uncovered object pixels and object pixels (every pixel without a mask). The fit reads it
        together with its losses (one host read).
        """
        if info.mask is None:
            uncovered = ~info.covered
            total = uncovered.new_full((), float(uncovered.numel()), dtype=torch.float64)  # a fill, no copy
        else:
            uncovered = info.mask & ~info.covered
            total = info.mask.sum().double()
        return torch.stack([uncovered.sum().double(), total])

    def step_pre_backward(self, info: StepInfo, counts: Sequence[float] | None = None) -> None:
        """Update the running coverage gap from the rendered view (``counts``: :meth:`coverage_counts`,
        already read to the host)."""
        if counts is None:
            counts = self.coverage_counts(info).tolist()  # host sync
        uncovered, total = counts
        gap = uncovered / max(1.0, total)
        self.gap = _GAP_EMA * self.gap + (1 - _GAP_EMA) * gap

    def step_post_backward(self, surfels: Surfels, info: StepInfo) -> None:
        """Accumulate screen-space gradients (warm-up) and view directions of the visible surfels."""
        out, cam = info.render, info.camera
        with torch.no_grad():
            visible = out.visibility > 0
            if info.stage == Stage.WARMUP and out.means2d.grad is not None:
                dens.accumulate_gradients(surfels, out.means2d.grad, visible, cam.width, cam.height)
            dev = surfels.means.device  # the centre is copied to the device once per camera, not per step
            center = cam.cached(("wtopo.fit.center", str(dev)),
                                lambda: torch.as_tensor(cam.center, dtype=torch.float32, device=dev))
            dens.accumulate_view_directions(surfels, center, visible)

    def _interval(self) -> int:
        """Iterations between density steps (``densify.interval``)."""
        return max(1, self.cfg.densify.interval or _DENSIFY_INTERVAL[1])  # None: a configuration not yet resolved

    def is_density_step(self, stage: Stage, it: int) -> bool:
        """Whether :meth:`step_end` runs density control at iteration ``it``."""
        start = stage_iteration(DENSIFY_START, self.warmup_end)
        return stage == Stage.WARMUP and it >= start and it % self._interval() == 0

    def step_end(self, stage: Stage, it: int, surfels: Surfels) -> bool:
        """Warm-up clone / split, prune and opacity reset on the ``densify`` schedule; returns whether
        the surfels changed."""
        dc, W = self.cfg.densify, self.warmup_end
        if not self.is_density_step(stage, it):
            return False
        changed = False
        with self.timers("densify"):
            if self.densify and it < DENSIFY_STOP * W:
                # scenes: the background covers every pixel, so no gap opens; the gradient decides
                if self.background is not None or self.gap > _GAP_THRESHOLD:
                    c, sp = dens.clone_and_split(surfels, ROI_EXTENT, self.cfg.runtime.max_surfels, self.gen)
                    self.record("densify", cloned=c, split=sp, gap=self.gap)
                    changed = True
                else:
                    self.record("densify_skipped", gap=self.gap)
                    surfels.buffers["grad_accum"].zero_()
                    surfels.buffers["grad_count"].zero_()
            removed = dens.prune_by_opacity(surfels, PRUNE_OPACITY)
            changed |= removed > 0
            if self.background is not None:
                near = prune_near_cameras(surfels, self.background)
                if near:
                    self.record("near_camera_prune", removed=near)
                changed |= near > 0
            reset_every = max(1, stage_iteration(dc.opacity_reset_fraction, W)) if dc.opacity_reset_fraction else 0
            if reset_every and is_reset_step(it, reset_every, self._interval()) and it < DENSIFY_STOP * W:
                if W - it >= _RESET_RECOVERY:
                    dens.reset_opacity(surfels, _OPACITY_RESET_VALUE)
                    self.record("opacity_reset", value=_OPACITY_RESET_VALUE)
                    changed = True
                else:  # too late: the surfels would reach the warm-up's end (the re-initialisation) still transparent
                    self.record("opacity_reset_skipped", remaining_warmup=W - it)
        return changed

    # -- mesh guidance --------------------------------------------------------------------------------
    def _mesh_guidance(self, s: Surfels, proxy: ProxyMesh) -> None:
        """Normal signs, geometry-aware prune and densification against a proxy of the current surfels."""
        co, dc, mc = self.cfg.coevolution, self.cfg.densify, self.cfg.mesh
        info = {}
        pm = None
        if co.enabled:
            with torch.no_grad():
                pm = proxy.build(s)
        if pm is None:
            # no proxy: mesh mode keeps the scaffold's signs and orients the others by the cameras
            info["signs"] = dens.align_normal_signs(s, NormalFlip(mc.normal_flip), generator=self.gen)
            self.record("mesh_guidance", **info)
            return
        verts, faces = pm.verts.detach(), pm.faces
        fid, dist, _ = proxy.closest(pm, s.means)
        fn, _ = dens.face_normals(verts, faces)
        mn = torch.where((fid >= 0)[:, None], fn[fid.clamp_min(0).long()], torch.zeros_like(s.means.detach()))
        info["signs"] = dens.align_normal_signs(s, NormalFlip(mc.normal_flip), mesh_normal=mn, distance=dist,
                                                distance_scales=_SIGN_DISTANCE, generator=self.gen)
        if dc.geometry_densify:
            info["spawned"] = dens.geometry_densify(s, verts, faces, fid, max_new=_GEOMETRY_DENSIFY_MAX,
                                                    max_surfels=self.cfg.runtime.max_surfels, generator=self.gen)
            dist = torch.cat([dist, torch.zeros(len(s) - dist.shape[0], dtype=dist.dtype, device=dist.device)])
        if dc.geometry_prune:
            if self.background is not None:  # background surfels are far from the proxy by design
                dist = torch.where(self.background.outside_roi(s.means), torch.zeros_like(dist), dist)
            info["pruned"] = dens.geometry_prune(s, dist, max_distance=_GEOMETRY_PRUNE_DISTANCE * ROI_EXTENT,
                                                 max_opacity=_GEOMETRY_PRUNE_OPACITY)
        self.record("mesh_guidance", **info)
