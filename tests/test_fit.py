# SPDX-License-Identifier: Apache-2.0
"""End-to-end fit on a tiny scene, the stage plan, resume after interruption, non-finite guards."""

import math

import numpy as np
import pytest
import torch
import trimesh
from fit_configs import small_fit_config

from wtopo import Scene, scenes
from wtopo.fitting import FitAborted, FitConfig, fit
from wtopo.fitting import loop as fit_loop
from wtopo.fitting import pixel_terms as fit_pixel_terms
from wtopo.fitting.checkpoint import list_checkpoints
from wtopo.fitting.evaluate import geometry_metrics
from wtopo.fitting.plan import make_plan

RESUME_TOL = 1e-5  # resumed vs uninterrupted parameters: same float32 operations in the same order


@pytest.fixture(scope="module")
def tiny():
    """A textured sphere, 10 views of 32 px plus 2 held-out views, masks, black background."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    return scenes.from_mesh(mesh, n_views=10, resolution=32, rig="sphere", texture="coffee", n_test=2, name="tiny")


def _config(warmup=30, coevolution=12):
    cfg = small_fit_config(warmup, coevolution, points=400, grids=(48, 48, 32), max_faces=1500, density_every=10,
                           eval_every=10, checkpoint_every=10)
    return cfg


def test_fit_tiny_scene_end_to_end(tiny, tmp_path):
    """Fit: the loss falls, the mesh is non-empty, watertight and closer to the truth than the start."""
    start = _config(0, 0)
    start.tsdf.enabled = False
    initial = fit(tiny, start, progress=False).mesh  # TSDF of the initial surfels: already near the visual hull
    res = fit(tiny, _config(100, 30), out_dir=tmp_path, progress=False)
    assert res.report["status"] == "completed" and res.report["iterations"] == 130
    photo = [h["losses"]["photo"] for h in res.history if "photo" in h.get("losses", {})]
    assert len(photo) >= 3 and photo[-1] < photo[0]
    assert len(res.mesh.faces) > 100 and res.mesh.is_watertight
    d_init = geometry_metrics(initial, tiny.gt_mesh)["chamfer_rel"]
    d_fit = geometry_metrics(res.mesh, tiny.gt_mesh)["chamfer_rel"]
    assert d_fit < d_init, (d_fit, d_init)
    assert {"chamfer", "f_score", "psnr"} <= set(res.history[-1])
    for name in ("mesh.ply", "surfels.ply", "history.json", "report.json", "plan.json"):
        assert (tmp_path / name).exists(), name
    # the mesh is returned in the scene's frame, not the internal unit cube
    np.testing.assert_allclose(res.mesh.bounds, tiny.gt_mesh.bounds, atol=0.25)


def test_plan_decisions_with_and_without_background(tiny):
    """Masked object: mask loss, no background rule; real background: the reverse; overrides win."""
    dev = torch.device("cpu")
    p = make_plan(tiny.normalized(), FitConfig(), dev)
    assert p.mask_loss > 0 and p.background_rule is False and p.background == (0.0, 0.0, 0.0)
    assert p.init_source == "cameras" and p.eval_views == 2
    open_scene = Scene(cameras=tiny.cameras, images=tiny.images, gt_mesh=tiny.gt_mesh, name="unmasked")
    cfg = FitConfig(sh_degree=2)
    q = make_plan(open_scene.normalized(), cfg, dev)
    assert q.mask_loss == 0.0 and q.background_rule is True
    assert q.sh_degree == 2 and "sh_degree" in q.overrides
    assert all(q.reasons[k] for k in q.decision_names())
    assert "background_rule" in str(q)


def test_the_plan_is_typed_frozen_and_the_resolved_config_carries_its_decisions(tiny):
    """The plan is a frozen dataclass of typed decisions; ``plan.json`` keeps one ``{value, reason, overridden}``
    per decision; ``str`` names the stages; every decision with a configuration field reaches the resolved
    configuration with the plan's value (one source of truth for the fit)."""
    import dataclasses
    import json

    from wtopo.fitting.config import InitSource
    from wtopo.fitting.plan import Plan, resolve_config
    from wtopo.fitting.scene_kind import SceneKind

    p = make_plan(tiny.normalized(), FitConfig(), torch.device("cpu"))
    assert isinstance(p, Plan) and isinstance(p.scene_kind, SceneKind) and isinstance(p.init_source, InitSource)
    assert isinstance(p.warmup_iterations, int)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.warmup_iterations = 3
    d = json.loads(json.dumps(p.to_dict()))
    assert list(d) == list(p.decision_names()) and d["scene_kind"] == {"value": "object", "reason":
                                                                        p.reasons["scene_kind"], "overridden": False}
    text = str(p)
    for stage in ("warm-up", "TSDF re-init", "co-evolution", "final mesh"):
        assert stage in text, stage
    r = resolve_config(FitConfig(), p)
    pairs = {"scene_kind": r.kind, "init_source": r.init.source, "mask_loss": r.losses.mask,
             "background_points": r.init.background_points, "background": r.background, "sh_degree": r.sh_degree,
             "multiview": r.losses.multiview, "densify": r.densify.enabled, "image_scale": r.runtime.image_scale,
             "warmup_iterations": r.warmup.iterations, "coevolution_iterations": r.coevolution.iterations,
             "means_decay_iterations": r.optim.means_decay_iterations, "means_restart": r.optim.means_restart,
             "max_surfels": r.runtime.max_surfels, "reinit_faces": r.tsdf.max_faces,
             "reinit_resolution": r.tsdf.resolution,
             "proxy_resolution": r.mesh.resolution, "final_resolution": r.final.resolution,
             "tsdf_reinit": r.tsdf.enabled, "mesh_loop": r.coevolution.enabled,
             "polish_iterations": r.polish.iterations,
             "proxy_level_sigma": r.mesh.level_sigma, "proxy_clip": r.mesh.clip_to_region, "preset": r.preset,
             "densify_interval": r.densify.interval, "filter_sigma": r.filter_sigma}
    for name, value in pairs.items():
        assert getattr(p, name) == value, name
    assert set(p.decision_names()) - set(pairs) == {"device", "region_of_interest", "mesh_policy", "background_rule",
                                                    "eval_views", "gt_metrics", "expected_seconds"}  # plan-only


def test_resume_after_interruption_matches_uninterrupted(tiny, tmp_path):
    """Stop at iteration 20, resume from the checkpoint: same surfels as one uninterrupted run."""
    full = fit(tiny, _config(), out_dir=tmp_path / "full", progress=False)
    cfg = _config()
    cfg.runtime.stop_at = 20
    part = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert part.report["status"] == "interrupted" and part.report["iterations"] == 20
    assert (tmp_path / "part" / "mesh.ply").exists() and list_checkpoints(tmp_path / "part" / "checkpoints")
    cfg.runtime.stop_at = None
    resumed = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert resumed.report["status"] == "completed" and resumed.report["iterations"] == 42
    assert len(resumed.surfels) == len(full.surfels)
    for k, v in full.surfels.params.items():
        torch.testing.assert_close(resumed.surfels.params[k], v, atol=RESUME_TOL, rtol=RESUME_TOL)


def test_a_branch_from_a_shared_warmup_equals_its_own_fit(tiny, tmp_path):
    """``runtime.start_from``: the loop's warm-up, stopped at its end, continued without the loop gives the
    surfels of a fit without the loop from scratch (on the CPU bit for bit: the warm-up is the same), and
    says where it started; a configuration whose warm-up differs, a checkpoint past the warm-up and a folder
    without checkpoints are refused, naming the cause."""
    def config(loop: bool):
        cfg = _config(10, 8)
        cfg.coevolution.enabled = loop
        return cfg

    alone = fit(tiny, config(False), out_dir=tmp_path / "alone", progress=False)
    src = config(True)
    src.runtime.stop_at = 10
    warm = fit(tiny, src, out_dir=tmp_path / "warm", progress=False)
    assert warm.report["status"] == "interrupted" and warm.report["iterations"] == 10
    cfg = config(False)
    cfg.runtime.start_from = str(tmp_path / "warm")
    branch = fit(tiny, cfg, out_dir=tmp_path / "branch", progress=False)
    assert branch.report["status"] == "completed" and branch.report["iterations"] == 18
    started = [e for e in branch.report["events"] if e["event"] == "started_from"]
    assert len(started) == 1 and started[0]["iteration"] == 10 and "warm" in started[0]["from"]
    assert len(branch.surfels) == len(alone.surfels) > 0
    for k, v in alone.surfels.params.items():
        torch.testing.assert_close(branch.surfels.params[k], v, atol=0, rtol=0)

    other = config(False)
    other.optim.means *= 2  # the warm-up reads it
    other.runtime.seed = 1
    other.runtime.start_from = str(tmp_path / "warm")
    with pytest.raises(ValueError, match=r"differs from this one.s in optim.means, runtime.seed"):
        fit(tiny, other, out_dir=tmp_path / "other", progress=False)
    late = config(False)
    late.runtime.start_from = str(tmp_path / "alone")  # a finished fit: its checkpoint is past the warm-up
    with pytest.raises(ValueError, match="a branch starts within the warm-up"):
        fit(tiny, late, out_dir=tmp_path / "late", progress=False)
    none = config(False)
    none.runtime.start_from = str(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="runtime.start_from = .*no usable checkpoint"):
        fit(tiny, none, out_dir=tmp_path / "none", progress=False)


def test_a_longer_coevolution_with_the_warmups_decay_horizon_branches_from_it(tiny, tmp_path):
    """A co-evolution longer than the source's, with the source's means' decay horizon
    (``optim.means_decay_iterations``), shares its warm-up: the branch equals the same configuration fitted
    from scratch (bit for bit on the CPU); without that horizon the warm-up's rates differ and the branch is
    refused, naming the field."""
    from wtopo.fitting.checkpointing import warmup_differences

    def config(coevo: int, horizon: int | None):
        cfg = _config(10, coevo)
        cfg.coevolution.enabled = False
        cfg.optim.means_decay_iterations = horizon
        return cfg

    src = config(8, None)
    src.runtime.stop_at = 10
    fit(tiny, src, out_dir=tmp_path / "warm", progress=False)
    longer = config(14, 18)  # 10 + 8: the source's horizon
    assert warmup_differences(src.to_dict(), longer.to_dict()) == []
    alone = fit(tiny, longer, out_dir=tmp_path / "alone", progress=False)
    longer.runtime.start_from = str(tmp_path / "warm")
    branch = fit(tiny, longer, out_dir=tmp_path / "branch", progress=False)
    assert branch.report["status"] == "completed" and branch.report["iterations"] == 24
    assert [e["iteration"] for e in branch.report["events"] if e["event"] == "started_from"] == [10]
    assert len(branch.surfels) == len(alone.surfels) > 0
    for k, v in alone.surfels.params.items():
        torch.testing.assert_close(branch.surfels.params[k], v, atol=0, rtol=0)
    plain = config(14, None)  # its rates decay over 24 iterations, the warm-up's included
    assert warmup_differences(src.to_dict(), plain.to_dict()) == ["coevolution.iterations"]
    plain.runtime.start_from = str(tmp_path / "warm")
    with pytest.raises(ValueError, match=r"in coevolution.iterations \(.*optim.means_decay_iterations = 18,"):
        fit(tiny, plain, out_dir=tmp_path / "plain", progress=False)
    assert warmup_differences(src.to_dict(), config(8, 30).to_dict()) == ["optim.means_decay_iterations"]
    unset = config(8, None)
    unset.coevolution.iterations = None  # left to the plan: no horizon to compare, so the field counts
    assert warmup_differences(src.to_dict(), unset.to_dict()) == ["coevolution.iterations"]


def test_injected_nan_is_survived_and_persistent_nan_aborts(tiny, tmp_path, monkeypatch):
    """Skip two NaN steps and finish; abort with a checkpoint when every step is NaN."""
    real = fit_pixel_terms.photometric
    calls = {"n": 0}

    def flaky(pred, target, dssim):
        calls["n"] += 1
        out = real(pred, target, dssim)
        return out * float("nan") if calls["n"] in (5, 6) else out

    monkeypatch.setattr(fit_pixel_terms, "photometric", flaky)
    res = fit(tiny, _config(20, 0), progress=False)
    assert res.report["non_finite_steps"] == 2 and res.report["status"] == "completed"
    assert all(torch.isfinite(p).all() for p in res.surfels.params.values())
    assert math.isfinite(float(np.asarray(res.mesh.vertices).sum()))

    monkeypatch.setattr(fit_pixel_terms, "photometric", lambda p, t, d: real(p, t, d) * float("nan"))
    cfg = _config(20, 0)
    monkeypatch.setattr(fit_loop, "MAX_CONSECUTIVE_FAILURES", 3)
    with pytest.raises(FitAborted, match="3 consecutive"):
        fit(tiny, cfg, out_dir=tmp_path, progress=False)
    assert list_checkpoints(tmp_path / "checkpoints")


class _NaNGradient(torch.autograd.Function):
    """Identity forward, non-finite gradient: a step whose loss is finite but whose update is not."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        return g * float("nan")


def test_non_finite_gradients_are_survived_without_a_second_host_read(tiny, monkeypatch):
    """A step with finite losses and NaN gradients is found with the next iteration's one read: the fit goes
    back to its last good state, never renders a non-finite parameter, and finishes; NaN gradients on every
    step abort after MAX_CONSECUTIVE_FAILURES."""
    real = fit_pixel_terms.photometric
    calls = {"n": 0}

    def flaky(pred, target, dssim):
        calls["n"] += 1
        assert torch.isfinite(pred).all(), "a non-finite update reached the renderer"
        out = real(pred, target, dssim)
        return _NaNGradient.apply(out) if calls["n"] in (5, 9) else out

    monkeypatch.setattr(fit_pixel_terms, "photometric", flaky)
    res = fit(tiny, _config(20, 0), progress=False)
    assert res.report["non_finite_steps"] == 2 and res.report["status"] == "completed"
    assert [e["why"] for e in res.report["events"] if e["event"] == "non_finite"] == ["step", "step"]
    assert all(torch.isfinite(p).all() for p in res.surfels.params.values())

    monkeypatch.setattr(fit_pixel_terms, "photometric", lambda p, t, d: _NaNGradient.apply(real(p, t, d)))
    monkeypatch.setattr(fit_loop, "MAX_CONSECUTIVE_FAILURES", 3)
    with pytest.raises(FitAborted, match="3 consecutive"):
        fit(tiny, _config(20, 0), progress=False)


def test_periodic_snapshots_read_nothing_and_keep_only_verified_steps(tiny, monkeypatch):
    """With a snapshot after every step, none of them reads the device (no settle: the state waits for the next
    iteration's one read to be verified), and a step whose gradients are NaN never becomes the last good state:
    the fit goes back to the state before it and finishes with the same failures as without snapshots."""
    real = fit_pixel_terms.photometric
    calls = {"n": 0}

    def flaky(pred, target, dssim):
        calls["n"] += 1
        out = real(pred, target, dssim)
        return _NaNGradient.apply(out) if calls["n"] in (5, 7, 11) else out

    settles, restored = [], []
    real_settle, real_restore = fit_loop.FitRun.settle, fit_loop.FitRun._restore

    def settle(self):
        settles.append(self.it)
        real_settle(self)

    def restore(self):
        restored.append({k: v.clone() for k, v in self.last_good[0].items() if isinstance(v, torch.Tensor)})
        real_restore(self)

    monkeypatch.setattr(fit_pixel_terms, "photometric", flaky)
    monkeypatch.setattr(fit_loop, "_SNAPSHOT_EVERY", 1)
    monkeypatch.setattr(fit_loop.FitRun, "settle", settle)
    monkeypatch.setattr(fit_loop.FitRun, "_restore", restore)
    res = fit(tiny, _config(20, 0), progress=False)
    assert res.report["non_finite_steps"] == 3 and res.report["status"] == "completed"
    assert set(settles) <= {0, 10, 20}, settles  # the start, densification and the stage's end: no snapshot
    assert len(restored) == 3
    # two failures in a row go back to the same verified state: the failed step's own snapshot was dropped
    assert all(torch.equal(restored[0][k], restored[1][k]) for k in restored[0])
    assert all(torch.isfinite(p).all() for p in res.surfels.params.values())


def test_late_opacity_reset_is_skipped(tiny, monkeypatch):
    """A reset with fewer than 100 warm-up iterations left is skipped and recorded; an early one runs."""
    from wtopo.fitting import _strategy as strategy

    cfg = _config(130, 0)
    cfg.tsdf.enabled = False
    cfg.densify.opacity_reset_fraction = 20 / 130  # every 20 iterations
    monkeypatch.setattr(strategy, "DENSIFY_START", 10 / 130)  # density steps (and resets) from iteration 10
    res = fit(tiny, cfg, progress=False)
    skipped = [e["iteration"] for e in res.report["events"] if e["event"] == "opacity_reset_skipped"]
    assert skipped == [40, 60, 80, 100], skipped  # 20 runs (110 left); DENSIFY_STOP 0.8 ends resets at 104
    ran = [e["iteration"] for e in res.report["events"] if e["event"] == "opacity_reset"]
    assert ran == [20], ran
    assert all(e["remaining_warmup"] < 100 for e in res.report["events"] if e["event"] == "opacity_reset_skipped")


@pytest.mark.parametrize("restart", [0.0, 1.0, 0.25, 1e-4])
def test_means_schedule_restarts_at_the_coevolution_when_asked(tiny, restart):
    """The means rate decays over both stages, or restarts at a fraction of ``optim.means`` for the
    co-evolution (never below where the single decay stands at its start)."""
    from wtopo.fitting.loop import FitRun

    cfg = _config(10, 10)
    cfg.optim.means_restart = restart
    run = FitRun(tiny, cfg, None, progress=False)
    run._start()
    o = run.cfg.optim

    def lr(it):
        run.it = it
        run._update_lr()
        return next(g["lr"] for g in run.opt.param_groups if g["name"] == "means")

    ratio = o.means_final / o.means
    single = o.means * ratio ** 0.5  # the single decay at the co-evolution's first iteration
    start = max(restart * o.means, single)
    assert lr(5) == pytest.approx(o.means * ratio ** 0.25)  # the warm-up is the same either way
    assert lr(10) == pytest.approx(start)
    assert lr(15) == pytest.approx(start * (o.means_final / start) ** 0.5)  # half-way down its own decay
    assert lr(20) == pytest.approx(o.means_final)
    if restart == 0.25:
        assert lr(10) == pytest.approx(0.25 * o.means)


def test_means_restart_saved_as_a_boolean_still_loads():
    """Configurations written when ``optim.means_restart`` was a boolean load as 0 / 1."""
    from wtopo.fitting.validate_config import validate_config

    for saved, want in ((False, 0.0), (True, 1.0)):
        cfg = FitConfig.from_dict({"optim": {"means_restart": saved}})
        assert cfg.optim.means_restart == want and type(cfg.optim.means_restart) is float
        validate_config(cfg)
    from wtopo.cli import _apply_set

    for text, want in (("true", 1.0), ("false", 0.0), ("0.3", 0.3)):  # --set lines of older commands too
        cfg = FitConfig()
        _apply_set(cfg, f"optim.means_restart={text}")
        assert cfg.optim.means_restart == want and type(cfg.optim.means_restart) is float
        validate_config(cfg)
    cfg = FitConfig()
    cfg.optim.means_restart = True  # set in code, a boolean is still refused by name
    with pytest.raises(TypeError, match="optim.means_restart"):
        validate_config(cfg)


def _coevolution_run(scene, losses: dict | None = None, mesh: dict | None = None):
    """A started fit (warm-up 10, co-evolution 8, the loop on) with the given ``losses`` and ``mesh`` fields
    set, to call its objective and step on a fixed state."""
    from wtopo.fitting.loop import FitRun

    cfg = _config(10, 8)
    cfg.coevolution.enabled = True
    for section, fields in (("losses", losses), ("mesh", mesh)):
        for k, v in (fields or {}).items():
            setattr(getattr(cfg, section), k, v)
    run = FitRun(scene, cfg, None, progress=False)
    run._start()
    return run


def _mesh_depth_terms(scene, field: str, values, **losses) -> tuple[list[torch.Tensor], object]:
    """The co-evolution's mesh-depth term on one fixed state (iteration 12, view 0) for each value of
    ``losses.<field>`` (the other ``losses`` fields given set first), and the run (to read gradients)."""
    from wtopo.fitting.stages import Stage

    run = _coevolution_run(scene, losses)
    out = []
    for v in values:
        setattr(run.cfg.losses, field, v)
        terms = run.objective(Stage.COEVOLUTION, 12, 0, run.surfels, run.proxy)
        assert terms.proxy_built and "mesh_depth" in terms.losses
        out.append(terms.losses["mesh_depth"])
    return out, run


def _assert_means_gradient(loss: torch.Tensor, run) -> None:
    run.surfels.means.grad = None
    loss.backward()
    g = run.surfels.means.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().max() > 0


def test_mesh_depth_debias_reaches_the_objective(tiny):
    """``losses.mesh_depth_debias`` changes the co-evolution's mesh-depth term on the same state, and
    only downwards (the median minimises the mean absolute deviation); its gradient is finite."""
    values, run = _mesh_depth_terms(tiny, "mesh_depth_debias", (False, True))
    plain, debiased = (float(v) for v in values)
    assert plain > 0 and debiased != plain and debiased <= plain * (1 + 1e-6)
    _assert_means_gradient(values[1], run)


def test_the_loop_computes_an_overflowing_step_again(tiny, monkeypatch):
    """The fit's step, told by the render that the deferred binning overflowed (as CUDA's does when its
    sort buffers were too small), computes the view again with the exact count and takes one step."""
    from wtopo.fitting.stages import Stage

    run = _coevolution_run(tiny)
    run.it = run.warmup_end + 2
    real = run.objective
    calls = []

    def overflowing(*args, defer_count=False, **kw):
        calls.append(defer_count)
        t = real(*args, defer_count=defer_count, **kw)
        t.render.overflow = torch.tensor(defer_count)  # the deferred call overflows, the exact one does not
        return t

    monkeypatch.setattr(run, "objective", overflowing)
    before = run.surfels.means.detach().clone()
    run._step(Stage.COEVOLUTION)
    assert calls == [True, False], "the step should have been computed again after the overflow"
    assert not torch.equal(run.surfels.means.detach(), before) and run.failures == 0


def test_final_grid_is_twice_as_fine_where_the_coevolution_found_thin_parts(tiny):
    """The plan's final TSDF grid doubles (up to the preset's finest) when the co-evolution's first thin-part
    measure exceeds FINAL_THIN_SHARE; an explicit final.resolution, a share at or below it, or no measure
    (scenes, no co-evolution) keep it."""
    from wtopo.fitting import presets
    from wtopo.fitting.loop import FINAL_THIN_SHARE, FitRun

    cfg = _config(10, 10)
    cfg.final.resolution = None
    run = FitRun(tiny, cfg, None, progress=False)
    base = int(run.cfg.final.resolution)
    hi = presets.budget(run.cfg.preset, run.device).final_grid[1]
    for info, want in [({}, base),
                       ({"thin_share": FINAL_THIN_SHARE, "resolution": 48, "limit": 0.15}, base),
                       ({"thin_share": FINAL_THIN_SHARE + 0.01, "resolution": 48, "limit": 0.15}, min(2 * base, hi)),
                       # the rule measured again on a finer proxy grid: its first measure decides
                       ({"thin_share": 0.01, "resolution": 96, "coarse": {"resolution": 48, "thin_share": 0.3}},
                        min(2 * base, hi))]:
        run.coevolution_info = info
        assert run._final_config().final.resolution == want, info
    assert run.cfg.final.resolution == base  # the fit's own configuration is not changed
    assert [e["event"] for e in run.events].count("final_grid_thin") == (2 if min(2 * base, hi) != base else 0)

    explicit = _config(10, 10)
    explicit.final.resolution = 40
    run = FitRun(tiny, explicit, None, progress=False)
    run.coevolution_info = {"thin_share": 0.5, "resolution": 48, "limit": 0.15}
    assert run._final_config().final.resolution == 40


def test_the_loop_freezes_the_heap_only_for_its_stages_and_never_someone_elses(tiny):
    """A fit's stages run with the objects alive at their start frozen out of the collector's generations and
    leave nothing frozen; a caller's own frozen objects stay frozen (the loop then freezes nothing)."""
    import contextlib
    import gc
    import unittest.mock as mock

    seen = []
    real = fit_loop.frozen_heap

    @contextlib.contextmanager
    def spy():
        with real() as froze:
            seen.append((froze, gc.get_freeze_count() > 0))
            yield froze

    with mock.patch.object(fit_loop, "frozen_heap", spy):
        fit(tiny, _config(6, 0), progress=False)
        assert seen and all(froze and frozen for froze, frozen in seen)
        assert gc.get_freeze_count() == 0
        seen.clear()
        gc.freeze()
        try:
            fit(tiny, _config(6, 0), progress=False)
            assert seen and not any(froze for froze, _ in seen)
            assert gc.get_freeze_count() > 0  # still the caller's (fewer: some of its objects were freed)
        finally:
            gc.unfreeze()
