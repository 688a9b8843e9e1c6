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
from wtopo.fitting import objective as fit_objective
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
    cfg.final.poisson_resolution = 48
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
    assert p["mask_loss"] > 0 and p["background_rule"] is False and p["background"] == (0.0, 0.0, 0.0)
    assert p["init_source"] == "cameras" and p["eval_views"] == 2
    open_scene = Scene(cameras=tiny.cameras, images=tiny.images, gt_mesh=tiny.gt_mesh, name="unmasked")
    cfg = FitConfig(sh_degree=2)
    q = make_plan(open_scene.normalized(), cfg, dev)
    assert q["mask_loss"] == 0.0 and q["background_rule"] is True
    assert q["sh_degree"] == 2 and q.decisions["sh_degree"].overridden
    assert all(d.reason for d in q.decisions.values())
    assert "background_rule" in str(q)


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


def test_the_suites_variants_change_only_what_acts_after_the_warmup():
    """benchmarks/hard.py's variants may branch from the default's warm-up (``--paired``)."""
    import importlib.util
    import pathlib

    from wtopo.fitting.checkpointing import warmup_differences

    path = pathlib.Path(__file__).parents[1] / "benchmarks" / "hard.py"
    spec = importlib.util.spec_from_file_location("hard_bench", path)
    hard = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hard)
    gpu = ["runtime.seed=3", "warmup.iterations=3000", "coevolution.iterations=2000",
           "optim.means_decay_iterations=4000"]  # the CUDA plan's
    base = hard._config("default", gpu).to_dict()
    assert len(hard.VARIANTS) >= 8
    for v in hard.VARIANTS:
        assert warmup_differences(base, hard._config(v, gpu).to_dict()) == [], v
    base = hard._config("default", ["runtime.seed=3"]).to_dict()
    assert warmup_differences(base, hard._config("default", ["runtime.seed=4"]).to_dict()) == ["runtime.seed"]
    assert warmup_differences(base, hard._config("default", ["runtime.seed=3", "warmup.iterations=7"]).to_dict()) == [
        "warmup.iterations"]


def test_injected_nan_is_survived_and_persistent_nan_aborts(tiny, tmp_path, monkeypatch):
    """Skip two NaN steps and finish; abort with a checkpoint when every step is NaN."""
    real = fit_objective.photometric
    calls = {"n": 0}

    def flaky(pred, target, dssim):
        calls["n"] += 1
        out = real(pred, target, dssim)
        return out * float("nan") if calls["n"] in (5, 6) else out

    monkeypatch.setattr(fit_objective, "photometric", flaky)
    res = fit(tiny, _config(20, 0), progress=False)
    assert res.report["non_finite_steps"] == 2 and res.report["status"] == "completed"
    assert all(torch.isfinite(p).all() for p in res.surfels.params.values())
    assert math.isfinite(float(np.asarray(res.mesh.vertices).sum()))

    monkeypatch.setattr(fit_objective, "photometric", lambda p, t, d: real(p, t, d) * float("nan"))
    cfg = _config(20, 0)
    cfg.runtime.max_consecutive_failures = 3
    with pytest.raises(FitAborted, match="3 consecutive"):
        fit(tiny, cfg, out_dir=tmp_path, progress=False)
    assert list_checkpoints(tmp_path / "checkpoints")


def test_late_opacity_reset_is_skipped(tiny):
    """A reset with fewer than 100 warm-up iterations left is skipped and recorded; an early one runs."""
    cfg = _config(130, 0)
    cfg.tsdf.enabled = False
    cfg.densify.opacity_reset_fraction = 20 / 130  # every 20 iterations
    cfg.densify.start_fraction = 10 / 130  # density steps (and resets) from iteration 10
    res = fit(tiny, cfg, progress=False)
    skipped = [e["iteration"] for e in res.report["events"] if e["event"] == "opacity_reset_skipped"]
    assert skipped == [40, 60, 80, 100], skipped  # 20 runs (110 left); stop_fraction 0.8 ends resets at 104
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


def _mesh_terms_around_iteration_14(scene, **losses):
    """The co-evolution's objective at iterations 13 and 14 (warm-up 10, co-evolution 8) with ``losses`` set."""
    from wtopo.fitting.stages import Stage

    run = _coevolution_run(scene, losses)
    return [run.objective(Stage.COEVOLUTION, it, 0, run.surfels, run.proxy) for it in (13, 14)]


def test_mesh_terms_wait_for_their_start_fraction(tiny):
    """With ``losses.mesh_start_fraction`` the mesh terms are off before that point of the co-evolution."""
    before, after = _mesh_terms_around_iteration_14(tiny, mesh_start_fraction=0.5)  # iteration 10 + 4
    assert not before.proxy_built and "mesh_depth" not in before.losses
    assert after.proxy_built and "mesh_depth" in after.losses


def test_mesh_terms_stop_at_their_end_fraction(tiny):
    """With ``losses.mesh_end_fraction`` the mesh terms are off from that point of the co-evolution on,
    and an end at or before the start is refused before anything runs."""
    from wtopo.fitting.validate_config import validate_config

    before, after = _mesh_terms_around_iteration_14(tiny, mesh_end_fraction=0.5)  # iteration 10 + 4
    assert before.proxy_built and "mesh_depth" in before.losses
    assert not after.proxy_built and "mesh_depth" not in after.losses
    cfg = _config(10, 8)
    cfg.losses.mesh_start_fraction = cfg.losses.mesh_end_fraction = 0.5
    with pytest.raises(ValueError, match="losses.mesh_end_fraction must be > .*losses.mesh_start_fraction"):
        validate_config(cfg)


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


def test_mesh_depth_robust_reaches_the_objective(tiny):
    """``losses.mesh_depth_robust`` (in proxy grid cells) changes the co-evolution's mesh-depth term on
    the same state, only downwards (``s log1p(x / s) <= x``), and less so the larger the scale; its
    gradient is finite and non-zero."""
    values, run = _mesh_depth_terms(tiny, "mesh_depth_robust", (0.0, 0.5, 50.0))
    assert run.proxy.cell > 0
    plain, tight, loose = (float(v) for v in values)
    assert plain > 0 and tight < loose <= plain * (1 + 1e-6)
    _assert_means_gradient(values[1], run)


def test_mesh_depth_robust_behind_reaches_the_objective(tiny):
    """``losses.mesh_depth_robust_behind`` changes the robust mesh-depth term on the same state: it lies
    between the two-sided robust term and the plain one (the pixels in front get the plain penalty back);
    without a robust scale it changes nothing; its gradient is finite and non-zero."""
    (both, behind), run = _mesh_depth_terms(tiny, "mesh_depth_robust_behind", (False, True), mesh_depth_robust=0.5)
    (plain, plain_behind), _ = _mesh_depth_terms(tiny, "mesh_depth_robust_behind", (False, True))
    assert float(plain_behind) == float(plain) > 0
    assert float(both) < float(behind) < float(plain)
    _assert_means_gradient(behind, run)


def _gated_views(run, gate: str) -> tuple[int, torch.Tensor | None]:
    """On four views of one state (iteration 12), the co-evolution's mesh-depth term with the objective's
    ``gate`` attribute in place and with it off: how many views it changed (to a non-zero term) and the
    last changed term (in the graph)."""
    from wtopo.fitting.stages import Stage

    obj, g = run.objective, getattr(run.objective, gate)
    changed, gated = 0, None
    for vi in range(4):
        on = obj(Stage.COEVOLUTION, 12, vi, run.surfels, run.proxy).losses["mesh_depth"]
        setattr(obj, gate, None)
        off = obj(Stage.COEVOLUTION, 12, vi, run.surfels, run.proxy).losses["mesh_depth"]
        setattr(obj, gate, g)
        if abs(float(on.detach()) - float(off.detach())) > 1e-6 and float(on.detach()) > 0:
            changed, gated = changed + 1, on
    return changed, gated


def test_mesh_photo_gate_reaches_the_objective(tiny):
    """``losses.mesh_photo_gate`` builds the gate (and not at 0) and changes the co-evolution's mesh-depth
    term on the same state by leaving pixels out (on at least one of four views: the tiny scene's early
    surfels and proxy disagree); the gated term's gradient is finite and non-zero."""
    from wtopo.fitting.loop import FitRun

    cfg = _config(10, 8)
    cfg.coevolution.enabled = True
    assert FitRun(tiny, cfg, None, progress=False).objective.photo_gate is None
    cfg.losses.mesh_photo_gate = 0.05  # proxy cells: the tiny early state disagrees by more
    run = FitRun(tiny, cfg, None, progress=False)
    run._start()
    assert run.objective.photo_gate is not None
    changed, gated = _gated_views(run, "photo_gate")
    assert changed >= 1
    _assert_means_gradient(gated, run)


def test_mesh_view_support_reaches_the_objective(tiny):
    """``losses.mesh_view_support`` builds the support (not at 0) and changes the co-evolution's mesh-depth
    term on the same state by leaving pixels out: at 2 on some view, and at more views than the scene has
    on every view (no pixel left: the term is 0); the kept maps of views not rendered yet come from the
    renderer; the gated term's gradient is finite and non-zero."""
    from wtopo.fitting.loop import FitRun
    from wtopo.fitting.stages import Stage

    cfg = _config(10, 8)
    cfg.coevolution.enabled = True
    assert FitRun(tiny, cfg, None, progress=False).objective.view_support is None
    cfg.losses.mesh_view_support = 2
    run = FitRun(tiny, cfg, None, progress=False)
    run._start()
    vs = run.objective.view_support
    assert vs is not None
    changed, gated = _gated_views(run, "view_support")
    n = len(run.train.cameras)
    assert len(vs._maps) == n  # every view rendered once for the count, or kept from its own step
    counts = vs.take_counts()
    assert counts["compared"] > 0 and 0 < counts["unsupported"] < counts["compared"]
    assert changed >= 1
    _assert_means_gradient(gated, run)
    vs.min_views = n + 1
    assert float(run.objective(Stage.COEVOLUTION, 12, 0, run.surfels, run.proxy).losses["mesh_depth"]) == 0.0


def test_mesh_depth_behind_reaches_the_objective(tiny):
    """``losses.mesh_depth_behind`` changes the co-evolution's mesh-depth term on the same state, only
    downwards and less the larger it is (0 keeps only the surfels in front of the proxy); its gradient
    is finite and non-zero."""
    values, run = _mesh_depth_terms(tiny, "mesh_depth_behind", (1.0, 0.5, 0.0))
    full, half, front = (float(v) for v in values)
    assert full > half > front > 0
    _assert_means_gradient(values[1], run)


def test_mesh_inset_reaches_the_objective(tiny):
    """``losses.mesh_inset`` (pixels) changes the co-evolution's mesh-depth term on the same state; an
    inset wider than any part of the image leaves no pixel to compare (the term is 0), and the gradient
    of a moderate inset is finite and non-zero."""
    values, run = _mesh_depth_terms(tiny, "mesh_inset", (0, 1, 50))
    full, inset, none = (float(v) for v in values)
    assert full > 0 and inset > 0 and inset != full and none == 0.0
    _assert_means_gradient(values[1], run)


def test_a_step_computed_again_counts_once(tiny):
    """The fit computes a step again after a binning overflow (CUDA's deferred count): what the first call
    folded into running state (the proxy's silhouette offset, the view support's counts) is put back by
    :meth:`Objective.retry_point`'s undo, so the step counts once; without it the offset moves twice."""
    from wtopo.fitting.stages import Stage

    # a gain of 0.2: three folds stay inside the offset's clamp
    run = _coevolution_run(tiny, {"mesh_view_support": 2}, {"silhouette_gain": 0.2})
    sil, vs = run.proxy.silhouette, run.objective.view_support
    assert sil is not None and vs is not None

    def step():
        terms = run.objective(Stage.COEVOLUTION, 12, 0, run.surfels, run.proxy)
        assert terms.proxy_built and "mesh_depth" in terms.losses
        return float(sil.value), vs.compared

    start = float(sil.value)
    undo = run.objective.retry_point(run.proxy)
    once = step()
    assert once[0] != start and once[1] > 0, "the step should move the offset and compare pixels"
    undo()
    assert float(sil.value) == start and vs.compared == 0
    assert step() == once  # computed again after the undo: the same state as one call
    twice = step()  # a third call without undo folds the view in once more (on a proxy moved by the first)
    assert abs(twice[0]) < sil.limit and twice[0] != once[0] and twice[1] > once[1]


def test_the_loop_undoes_a_step_it_computes_again(tiny, monkeypatch):
    """The fit's step, told by the render that the deferred binning overflowed (as CUDA's does when its
    sort buffers were too small), computes the view again with the exact count and leaves the proxy's
    silhouette offset where one call leaves it."""
    from wtopo.fitting.stages import Stage

    run = _coevolution_run(tiny, {"mesh_view_support": 2}, {"silhouette_gain": 0.2})
    run.it = run.warmup_end + 2
    sil, real = run.proxy.silhouette, run.objective
    vs = real.view_support
    calls = []

    def overflowing(*args, defer_count=False, **kw):
        calls.append(defer_count)
        t = real(*args, defer_count=defer_count, **kw)
        t.render.overflow = torch.tensor(defer_count)  # the deferred call overflows, the exact one does not
        return t

    start = float(sil.value)
    one = real.retry_point(run.proxy)
    real(Stage.COEVOLUTION, run.it, run._view(run.it), run.surfels, run.proxy)
    expected, compared = float(sil.value), vs.compared
    one()
    assert expected != start and compared > 0
    monkeypatch.setattr(run, "objective", overflowing)
    monkeypatch.setattr(overflowing, "retry_point", real.retry_point, raising=False)
    run._step(Stage.COEVOLUTION)
    assert calls == [True, False], "the step should have been computed again after the overflow"
    assert float(sil.value) == expected and vs.compared == compared


def test_silhouette_options_run_in_a_fit(tiny):
    """The proxy's silhouette offset (mesh.silhouette_gain) and the final calibration both run on a masked
    fit: the offset is recorded at the mesh guidance, the calibration's move is recorded and bounded."""
    cfg = _config(30, 12)
    cfg.mesh.silhouette_gain = 0.3
    cfg.final.silhouette_calibration = True
    res = fit(tiny, cfg, progress=False)
    guidance = [e for e in res.report["events"] if e["event"] == "mesh_guidance"]
    assert guidance and all("silhouette_offset" in e for e in guidance)
    assert guidance[-1]["silhouette_offset"] != 0.0, "the co-evolution should have measured the proxy's rim"
    cal = [e for e in res.report["events"] if e["event"] == "silhouette_calibration"]
    assert len(cal) == 1 and len(cal[0]["rounds"]) >= 1 and abs(cal[0]["offset_px"]) <= 1.0 + 1e-6
    assert len(res.mesh.faces) > 100


def test_halo_target_and_carved_closure_run_in_a_fit(tiny):
    """losses.mask_halo and final.closure=carve run on a masked fit: the final mesh is closed by the
    carving fusion itself (no Poisson re-mesh) and recorded as such."""
    cfg = _config(30, 12)
    cfg.losses.mask_halo = True
    cfg.final.closure = "carve"
    res = fit(tiny, cfg, progress=False)
    policy = [e for e in res.report["events"] if e["event"] == "mesh_policy"]
    assert policy and policy[-1]["closure"] == "carve"
    assert not any(e["event"] == "poisson_remesh" for e in res.report["events"])
    assert res.mesh.is_watertight and len(res.mesh.faces) > 100


def test_restart_along_normal_damps_in_plane_motion_in_the_fit(tiny, monkeypatch):
    """In a restarted co-evolution with ``means_restart_along_normal`` the loop scales each means
    step's in-plane part by the single decay's share of the rate; the warm-up is left alone."""
    from wtopo.fitting import loop as fit_loop
    from wtopo.fitting.schedule import damp_in_plane_steps, means_rate

    cfg = _config(10, 10)
    cfg.optim.means_restart, cfg.optim.means_restart_along_normal = 1.0, True
    run = fit_loop.FitRun(tiny, cfg, None, progress=False)
    calls = []

    def recording(means, before, normals, scale):
        raw = means.detach().clone()
        damp_in_plane_steps(means, before, normals, scale)
        calls.append((run.it, before, normals, raw, means.detach().clone(), scale))

    monkeypatch.setattr(fit_loop, "damp_in_plane_steps", recording)
    run.run()
    assert calls, "the co-evolution took no shaped step"
    assert min(c[0] for c in calls) >= run.warmup_end  # never in the warm-up
    assert len(calls) == run.total_iterations - run.warmup_end  # every co-evolution step
    moved = 0.0
    for it, before, normals, raw, shaped, scale in calls:
        assert scale == pytest.approx(means_rate(cfg.optim, it, run.warmup_end, run.total_iterations)[1])
        # float32 rounding of means of size M: the damped means carry up to 1.5 eps M per component (a sum of
        # three terms), the raw ones 0.5 eps M; the part along a unit normal sums three components (sqrt(3))
        # and the in-plane part subtracts it again: 6 eps M bounds the difference of both parts
        tol = 6 * torch.finfo(torch.float32).eps * float(torch.maximum(before.abs(), raw.abs()).max())
        torch.testing.assert_close(((shaped - before) * normals).sum(-1), ((raw - before) * normals).sum(-1),
                                   atol=tol, rtol=0)
        raw_in = (raw - before) - ((raw - before) * normals).sum(-1, keepdim=True) * normals
        got_in = (shaped - before) - ((shaped - before) * normals).sum(-1, keepdim=True) * normals
        torch.testing.assert_close(got_in, scale * raw_in, atol=tol, rtol=0)
        moved = max(moved, float(raw_in.norm(dim=-1).max()))
    assert calls[0][5] < 0.5 and moved > 0  # a real damping of a real in-plane motion
