# SPDX-License-Identifier: Apache-2.0
"""The fit loop: warm-up, TSDF re-initialisation, co-evolution with the proxy mesh, polish, final mesh.

:class:`FitRun` owns the state of one fit (surfels, optimiser, iteration, history, events) and
drives the stages; its collaborators each do one thing: :class:`~.objective.Objective` (the loss
terms of an iteration), :class:`~._strategy.DensityStrategy` (density control and mesh guidance),
:func:`~._reinit.tsdf_reinit` and :func:`~._final_mesh.final_mesh` (the discrete stages), :class:`~.evaluate.Evaluator`,
:class:`~.checkpointing.Checkpointer` (checkpoints on an iteration and a wall-clock cadence,
resume), :class:`~._timeline.FitTimeline` (USD) and :mod:`._progress` (bars, SIGINT / SIGTERM).
The non-finite guard lives here: a step with a non-finite loss, gradient or parameter is skipped
and the last good state restored; too many in a row abort with a checkpoint.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from pathlib import Path

import torch
import trimesh

from .._profile import section
from .._validate import trusted_values
from . import presets as _presets
from ._final_mesh import final_mesh
from ._init_surfels import revise_plan, scene_surfels
from ._progress import StageBar, StopRequest, frozen_heap
from ._reinit import tsdf_reinit
from ._run_state import restore_run_state, run_state
from ._strategy import DensityStrategy, StepInfo
from ._timeline import FitTimeline, aborted_on_failure
from .adam import Adam
from .background import BackgroundState, contract_steps
from .checkpointing import Checkpointer
from .config import FitConfig, config_hash
from .evaluate import Evaluator
from .objective import LossLog, Objective
from .plan import Plan, make_plan, resolve_config, split_views
from .profiling import Timers
from .proxy import ProxyMesh, ProxyResult, region_clip
from .schedule import means_rate
from .stages import Renderer, Stage
from .surfels import Surfels
from .thin_parts import thin_parts

__all__ = ["FitRun", "FitAborted"]

_SNAPSHOT_EVERY = 25  # iterations between in-memory "last good" snapshots
FINAL_THIN_SHARE = 0.10  # thin share above which the final TSDF grid is twice as fine (design/decisions.md)
MAX_CONSECUTIVE_FAILURES = 20  # non-finite steps in a row after which the fit aborts (with a checkpoint)
_SH_REST_LR = 5e-4  # learning rate of the higher SH bands: 1/20 of the DC rate, as 3DGS


class FitAborted(RuntimeError):
    """Too many consecutive non-finite steps; a checkpoint of the last good state was written."""


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _lrs(cfg: FitConfig) -> dict[str, float]:
    o = cfg.optim
    return {"means": o.means, "quats": o.quats, "log_scales": o.scales, "opacity_logits": o.opacities,
            "sh_dc": o.sh_dc, "sh_rest": _SH_REST_LR}


def _split_views(sc, eval_views: int):
    """Training and held-out subsets of ``sc`` (:func:`~.plan.split_views`) and whether the latter is really
    held out: with nothing held out, every fourth training view is used for evaluation."""
    train, test = split_views(sc, eval_views)
    return sc.subset(train), (sc.subset(test) if test else sc.subset(train[:: max(1, len(train) // 4)])), bool(test)


class FitRun:
    """One fit of a scene. Use :func:`wtopo.fit`; this class is its engine.

    Args:
        scene: the user's :class:`wtopo.Scene` (world frame).
        cfg: configuration.
        out_dir: run directory (checkpoints, outputs) or ``None``.
        progress: tqdm progress bars and the printed plan.

    Attributes:
        plan: the stage plan of the scene.
        surfels: the current surfels (internal frame); replaced when a failed step is rolled back.
        it: iterations done.
        history: one record per evaluation.
        events: discrete events (densify, re-initialisation, guidance, failures, signals, resume).
        status: ``"running"``, ``"completed"``, ``"interrupted"`` or ``"aborted"``.
        proxy: the proxy-mesh builder; ``proxy_mesh`` its last mesh built for the losses.
    """

    def __init__(self, scene, cfg: FitConfig, out_dir: str | Path | None, progress: bool):
        self.cfg = cfg
        self.progress = progress and cfg.runtime.progress
        self.out_dir = None if out_dir is None else Path(out_dir)
        self.device = _resolve_device(cfg.runtime.device)
        # runtime.profile on CUDA: every section waits for the device (no synchronisation otherwise)
        profile_sync = cfg.runtime.profile and self.device.type == "cuda"
        self.timers = Timers((lambda: torch.cuda.synchronize(self.device)) if profile_sync else None)
        self.t_start = time.perf_counter()
        self.elapsed_before = 0.0
        with self.timers("setup"):
            self._setup(scene, cfg)

    def _setup(self, scene, cfg: FitConfig) -> None:
        """The plan, the scene on the device and the fit's collaborators (the profile's ``setup``)."""
        self.sim = scene.normalization()
        internal = scene.normalized().to(self.device)
        self.plan: Plan = make_plan(internal, cfg, self.device)
        user_cfg, cfg = cfg, resolve_config(cfg, self.plan)  # fields left to the plan (None) filled in
        self.cfg = cfg
        scale = float(cfg.runtime.image_scale)
        if scale < 1.0:
            internal = internal.downscaled(1.0 / scale)
        self.train, self.test, held_out = _split_views(internal, self.plan.eval_views)
        self.hash = config_hash(user_cfg)
        self.final_grid_auto = user_cfg.final.resolution is None  # the plan's: finer where parts are thin
        self.gen = torch.Generator().manual_seed(cfg.runtime.seed)
        from ..rasterize import RasterConfig

        bg = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.render = Renderer(bg, RasterConfig(filter_sigma=cfg.filter_sigma), graphs=not cfg.runtime.profile)
        self.it = 0
        self.tsdf_done = False
        self.history: list[dict] = []
        self.events: list[dict] = []
        self.failures = 0
        self.total_failures = 0
        self.loss_log = LossLog()
        self.proxy: ProxyMesh = ProxyMesh(cfg.mesh, clip=region_clip(cfg.mesh, self.plan.layout))
        self.proxy_mesh: ProxyResult | None = None
        self.tsdf_info: dict = {}
        self._epoch_order: tuple[int, list[int]] = (-1, [])  # (epoch, its view order): see _view
        self.coevolution_info: dict = {}  # the thin-part rule's measure and decision (thin_parts)
        self.status = "running"
        self.surfels: Surfels | None = None
        self.opt: Adam | None = None
        self.last_good: tuple[dict, dict] | None = None  # (surfel, optimiser) state dicts of the last good step
        # whether the last step's gradients and parameters are finite: a device flag read with the next
        # iteration's losses (one host read per iteration), or by settle() before the state is used
        self._unverified: torch.Tensor | None = None
        self._pending_good: tuple[dict, dict] | None = None  # a snapshot of the unverified step (_snapshot_unread)
        self.objective = Objective(cfg, self.train, render=self.render, mask_weight=float(cfg.losses.mask),
                                   warmup_end=self.warmup_end, timers=self.timers,
                                   roi_center=self.plan.layout.roi_center,
                                   mesh_every=_presets.budget(cfg.preset, self.device).mesh_every)
        # scenes keep a background: contracted steps outside the region, nothing on the lenses
        self.background = BackgroundState(self.plan.layout, self.device) if self.plan.background_rule else None
        self.strategy = DensityStrategy(cfg, densify=bool(cfg.densify.enabled), warmup_end=self.warmup_end,
                                        generator=self.gen, record=self.record, timers=self.timers,
                                        background=self.background)
        self.evaluator = Evaluator(self.test, internal.gt_mesh, render=self.render, enabled=self.plan.gt_metrics,
                                   seed=cfg.runtime.seed, images=cfg.runtime.eval_metrics, held_out=held_out)
        self.checkpoints = Checkpointer(self, self.out_dir)
        self.stop = StopRequest(lambda signum: self.record("signal", signal=signum))
        self.timeline: FitTimeline | None = None

    @property
    def warmup_end(self) -> int:
        """Iteration at which the warm-up stage ends (``cfg.warmup.iterations``)."""
        return int(self.cfg.warmup.iterations)

    @property
    def total_iterations(self) -> int:
        """Iterations of warm-up plus co-evolution."""
        return self.warmup_end + int(self.cfg.coevolution.iterations)

    @property
    def polish_end(self) -> int:
        """Iteration at which the polish ends and the final mesh is made (``polish.iterations`` after the
        co-evolution)."""
        return self.total_iterations + int(self.cfg.polish.iterations or 0)

    def elapsed(self) -> float:
        """Wall seconds of this fit, including those before the checkpoint it resumed from."""
        return self.elapsed_before + time.perf_counter() - self.t_start

    def record(self, event: str, **fields) -> None:
        """Append an event at the current iteration."""
        self.events.append({"iteration": self.it, "event": event, **fields})

    def _view(self, it: int) -> int:
        """The training view of iteration ``it``: each epoch a permutation of the views seeded by the epoch (a
        function of ``it`` alone, so a resumed fit draws the same views); the epoch's order is kept."""
        n = len(self.train.cameras)
        epoch, k = divmod(it, n)
        if self._epoch_order[0] != epoch:
            g = torch.Generator().manual_seed(self.cfg.runtime.seed * 1_000_003 + epoch)
            self._epoch_order = (epoch, torch.randperm(n, generator=g).tolist())
        return self._epoch_order[1][k]

    # -- optimiser ---------------------------------------------------------------------------------
    def set_surfels(self, surfels: Surfels, opt_state: dict | None = None) -> None:
        """Make ``surfels`` the fitted ones, with a fresh optimiser (or ``opt_state``), and the last good state."""
        self.surfels = surfels
        self.opt = surfels.optimizer(_lrs(self.cfg))
        if opt_state is not None:
            self.opt.load_state_dict(opt_state)
        self.snapshot()

    def snapshot(self) -> None:
        """Keep the current surfels and optimiser as the last good state (after :meth:`settle`: a step not yet
        known to be finite is checked first). Parameters and moments are copied on the fit's device (the live
        ones change in place; a checkpoint moves them to the host when it writes)."""
        self.settle()
        self.last_good = self._state_copy()

    def _state_copy(self) -> tuple[dict, dict]:
        """Copies of the surfels' and the optimiser's state, on the fit's device."""
        return self.surfels.state_dict(self.device), copy.deepcopy(self.opt.state_dict())

    def _snapshot_unread(self) -> None:
        """The periodic snapshot without a host read: the state is copied now and becomes the last good one when
        the next read finds this step finite (:meth:`_verdict`); a step already known good is kept at once."""
        if self._unverified is None:
            self.snapshot()
            return
        self._pending_good = self._state_copy()

    def settle(self) -> None:
        """Read whether the last step left finite gradients and parameters (one host read when a step is
        unverified); a non-finite step is a failure and the last good state comes back."""
        flag, self._unverified = self._unverified, None
        if flag is not None:
            self._verdict(bool(flag))

    def _verdict(self, finite: bool) -> bool:
        """Act on the last step's flag once read: a finite step ends a run of failures, a non-finite one is a
        failure (the last good state comes back). Returns ``finite``."""
        pending, self._pending_good = self._pending_good, None
        if finite:
            self.failures = 0
            if pending is not None:
                self.last_good = pending
        else:
            self._failure("step", {})
        return finite

    def _restore(self) -> None:
        sd, od = self.last_good
        self.surfels = Surfels.from_state_dict(sd, self.device)
        self.opt = self.surfels.optimizer(_lrs(self.cfg))
        self.opt.load_state_dict(od)

    # -- checkpoints (written and read by the Checkpointer) ------------------------------------------
    def checkpoint_state(self) -> dict:
        """The stored dictionary (:func:`~._run_state.run_state`)."""
        return run_state(self)

    def restore_checkpoint(self, st: dict) -> None:
        """Load a stored dictionary (:meth:`checkpoint_state`) into this fit."""
        restore_run_state(self, st)

    def _update_lr(self) -> None:
        """Set the means' rate for this iteration."""
        lr = means_rate(self.cfg.optim, self.it, self.warmup_end, self.total_iterations,
                        thin="coarse" in self.coevolution_info)
        for g in self.opt.param_groups:
            if g["name"] == "means":
                g["lr"] = lr

    # -- one iteration ---------------------------------------------------------------------------------
    def _failure(self, why: str, terms: dict[str, float]) -> None:
        self._unverified = None
        self._pending_good = None
        self.failures += 1
        self.total_failures += 1
        self.record("non_finite", why=why, terms=terms)
        self.opt.zero_grad(set_to_none=True)
        self._restore()
        if self.failures >= MAX_CONSECUTIVE_FAILURES:
            self.status = "aborted"
            path = self.checkpoints.save(force=True)
            raise FitAborted(f"{self.failures} consecutive non-finite steps at iteration {self.it} ({why}); "
                             f"last good state checkpointed to {path}")

    def _step(self, stage: Stage) -> None:
        vi = self._view(self.it)
        mask = None if self.train.masks is None else self.train.masks[vi]
        # the binning sizes its buffers from earlier views (no read of this view's pair count); an
        # overflow, read below with the losses, renders the view again with the exact count
        for defer in (True, False):
            t = self.objective(stage, self.it, vi, self.surfels, self.proxy, defer_count=defer)
            info = StepInfo(stage, t.render, t.covered, mask, self.train.cameras[vi])
            with self.timers("read"):
                extra = [self.strategy.coverage_counts(info)]
                if self._unverified is not None:
                    extra.append(self._unverified.double().view(1))
                if t.render.overflow is not None:
                    extra.append(t.render.overflow.double().view(1))
                # host sync: the one read of an iteration (loss terms, coverage, the last step's finiteness, overflow)
                stacked = torch.stack(list(t.losses.values()))  # the terms, once: read here, summed for backward
                total = stacked.sum()  # one op, not one addition per term
                read = torch.cat([stacked.detach().double(), *extra]).tolist()
            if self._unverified is not None:  # the last step: its failure discards this forward too
                self._unverified = None
                if not self._verdict(bool(read[len(t.losses) + 2])):
                    return
            if t.render.overflow is None or not read[-1]:
                break
        if t.proxy_built:
            self.proxy_mesh = t.proxy
        nl = len(t.losses)
        self.strategy.step_pre_backward(info, read[nl:nl + 2])
        terms = dict(zip(t.losses, read[:nl]))
        if not math.isfinite(sum(terms.values())):
            self._failure("loss", {k: v for k, v in terms.items() if not math.isfinite(v)})
            return
        with self.timers("backward"):
            total.backward()
        with self.timers("optimizer"):
            # whether this step is finite is a device flag, read with the next iteration's losses (no host read
            # here); the optimiser zeroes a gradient's non-finite elements before its update, so that the next
            # forward never sees a non-finite parameter before the flag sends the fit back to its last good state
            self._update_lr()
            before = self.surfels.means.detach().clone() if self.background is not None else None
            finite = self.opt.step()
            if finite is None:
                finite = torch.ones((), dtype=torch.bool, device=self.surfels.means.device)
            if self.background is not None:
                contract_steps(self.surfels.means, before, self.background.step_scale(before))
                finite = finite & torch.isfinite(self.surfels.means.detach()).all()
            self._unverified = finite
        with self.timers("statistics"):
            self.strategy.step_post_backward(self.surfels, info)
        self.loss_log.add(terms, first=self.loss_log.count == 0 and not self.history)
        if self.it % _SNAPSHOT_EVERY == 0:
            with self.timers("snapshot"):
                self._snapshot_unread()
        with self.timers("release"):  # the step's gradients, images and render buffers are freed here
            self.opt.zero_grad(set_to_none=True)
            del t, info, stacked, total

    # -- stages ------------------------------------------------------------------------------------------
    def _iterate(self, stage: Stage, start: int, end: int) -> None:
        rt = self.cfg.runtime
        bar = StageBar(self.progress, stage.value, start, end, self.it)
        try:
            with frozen_heap():
                while self.it < end and not self.stop.requested:
                    with trusted_values():  # the fit's own tensors, checked by its guards after every step
                        if self.strategy.step_pre_forward(stage, self.it, self.surfels, self.proxy):
                            self.snapshot()
                        self._step(stage)
                    if self.strategy.step_end(stage, self.it, self.surfels):
                        self.snapshot()
                    self.it += 1
                    if self.timeline is not None and self.it % self.timeline.every == 0:
                        self.settle()
                        self.timeline.sample(self.it, self.surfels, self.proxy_mesh)
                    if rt.eval_every and self.it % rt.eval_every == 0:
                        self.settle()
                        self._evaluate(stage)
                    self.checkpoints.maybe_save()
                    if rt.stop_at is not None and self.it >= rt.stop_at:
                        self.stop.request()
                    bar.update(self.it, self._bar_status)
                self.settle()
        finally:
            bar.close()

    def _bar_status(self) -> dict:
        return {"loss": f"{self.loss_log.ema:.4f}", "surfels": len(self.surfels),
                "faces": 0 if self.proxy_mesh is None else self.proxy_mesh.num_faces,
                "elapsed": f"{self.elapsed():.0f}s"}

    def _start(self) -> None:
        """Open the timeline (its writer process starts while the rest goes on), then resume from the run
        directory's checkpoints or draw the initial surfels."""
        self.timeline = FitTimeline.open(self.out_dir, self.cfg.runtime.usd_every, self.sim, self.train.cameras,
                                         self.timers)
        resumed = self.checkpoints.resume()
        if resumed and self.timeline is not None:
            self.timeline.carry_over(self.it)
        if not resumed:
            with self.timers("init"):
                s = scene_surfels(self.train, self.cfg, self.plan.layout, self.device, self.gen, self.background,
                                  self.record, forced="background_points" in self.plan.overrides)
                with section("init_setup"):
                    self.set_surfels(s)
        self.plan = revise_plan(self.plan, self.events)
        if self.progress:
            print(self.plan)
            if resumed:
                print(f"resuming at iteration {self.it}")

    def _tsdf_reinit(self) -> None:
        with self.timers("tsdf"):
            r = tsdf_reinit(self.surfels, self.train.cameras, self.cfg, render=self.render,
                            background_rule=self.plan.background_rule, record=self.record,
                            layout=self.plan.layout)
            self.tsdf_info = r.info
            if r.proxy is not None:
                self.proxy = r.proxy
            if r.surfels is not None:
                self.set_surfels(r.surfels)
        self.tsdf_done = True

    def _thin_parts(self) -> None:
        """At the co-evolution's start: measure the proxy's thin parts and decide its grid and the mesh terms
        once (a resumed fit keeps the decision its checkpoint holds)."""
        if "mesh_terms" not in self.coevolution_info:
            with self.timers("thin_parts"):
                self.coevolution_info = thin_parts(self.proxy, self.surfels, self.train.cameras, self.cfg)
            if self.coevolution_info:
                self.record("thin_parts", **self.coevolution_info)
        res = self.coevolution_info.get("resolution")
        if res is not None and int(res) != int(self.proxy.cfg.resolution):
            self.proxy = self.proxy.with_resolution(int(res))
        self.objective.mesh_terms = bool(self.coevolution_info.get("mesh_terms", True))

    def _final_config(self) -> FitConfig:
        """The configuration of the final mesh: the plan's TSDF grid twice as fine (up to the preset's finest)
        when more than :data:`FINAL_THIN_SHARE` of what the views see is thin on the co-evolution's first proxy
        grid (:mod:`.thin_parts`: under 3 proxy cells, about 6 pixel footprints, thick; fused at 0.8 footprints
        per voxel with a 4-voxel truncation, such a part's two sides share one band and it erodes); an explicit
        ``final.resolution`` stays."""
        info = self.coevolution_info
        share = info.get("coarse", info).get("thin_share")
        if not self.final_grid_auto or share is None or share <= FINAL_THIN_SHARE:
            return self.cfg
        hi = _presets.budget(self.cfg.preset, self.device).final_grid[1]
        res = min(2 * int(self.cfg.final.resolution), hi)
        if res == int(self.cfg.final.resolution):
            return self.cfg
        self.record("final_grid_thin", resolution=res, thin_share=share)
        return dataclasses.replace(self.cfg, final=dataclasses.replace(self.cfg.final, resolution=res))

    def _final_mesh(self) -> trimesh.Trimesh:
        with self.timers("final"):
            guided = self.cfg.coevolution.enabled and self.it > self.warmup_end
            return final_mesh(self.surfels, self.train.cameras, self._final_config(), render=self.render,
                              proxy=self.proxy, guided=guided, tsdf_info=self.tsdf_info, record=self.record,
                              layout=self.plan.layout, masks=self.train.masks,
                              thin=not self.coevolution_info.get("mesh_terms", True))

    def _evaluate(self, stage: Stage, mesh: trimesh.Trimesh | None = None) -> dict:
        with self.timers("evaluate"):
            rec = {"iteration": self.it, "stage": stage.value, "elapsed": round(self.elapsed(), 3),
                   "stage_times": {k: round(v, 3) for k, v in self.timers.total.items()},
                   "losses": self.loss_log.take(), "surfels": len(self.surfels),
                   "proxy_faces": 0 if self.proxy_mesh is None else self.proxy_mesh.num_faces}
            proxy = None if stage == Stage.POLISH else self.proxy_mesh  # the polish's surfels leave the proxy
            rec.update(self.evaluator(self.surfels, mesh=mesh, proxy=proxy))
        self.history.append(rec)
        return rec

    def run(self) -> trimesh.Trimesh:
        """Run (or resume) every stage; returns the final mesh in the internal frame."""
        with self.stop.installed(), aborted_on_failure(lambda: self.timeline):
            self._start()
            self._iterate(Stage.WARMUP, 0, self.warmup_end)
            if not self.stop.requested and not self.tsdf_done and self.cfg.tsdf.enabled:
                self._tsdf_reinit()
                self._evaluate(Stage.TSDF)
            if not self.stop.requested and self.warmup_end <= self.it < self.total_iterations:
                self._thin_parts()
                self._iterate(Stage.COEVOLUTION, self.warmup_end, self.total_iterations)
            if not self.stop.requested and self.total_iterations <= self.it < self.polish_end:
                # the surfels on the photographs alone (the objective's mesh terms and the strategy act only in
                # the co-evolution), released from the proxy's pull before the final mesh is fused from them
                if self.it == self.total_iterations:
                    self.snapshot()  # a failed step in the polish comes back to the surfels the loop left
                self._iterate(Stage.POLISH, self.total_iterations, self.polish_end)
            if self.it > 0:  # as in the other stages, the checkpoint holds no record of a stop
                self.checkpoints.save_once()
            mesh = self._final_mesh()
            self._evaluate(Stage.FINAL, mesh=mesh)
            self.status = "interrupted" if self.stop.requested else "completed"
            if self.timeline is not None:
                self.timeline.close(mesh)
                if self.timeline.failure is not None:  # the fit went on without it (warned)
                    self.record("timeline_failed", error=self.timeline.failure)
        return mesh
