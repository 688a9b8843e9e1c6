# SPDX-License-Identifier: Apache-2.0
"""The polish (``FitConfig.polish``): photometric iterations after the co-evolution that move the surfels, their
held-out PSNR and the final mesh fused from them last; resumable within it; planned only after a proxy-mesh loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from fit_configs import small_fit_config

from wtopo import scenes
from wtopo.fitting import FitConfig, SceneKind, fit, fit_surfels
from wtopo.fitting.plan import make_plan

RESUME_TOL = 1e-5  # resumed vs uninterrupted parameters: the same float32 operations in the same order


@pytest.fixture(scope="module")
def tiny():
    """A textured sphere, 10 views of 32 px plus 2 held-out views, masks, black background."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    return scenes.from_mesh(mesh, n_views=10, resolution=32, rig="sphere", texture="coffee", n_test=2, name="tiny")


def _config(polish: int) -> FitConfig:
    return small_fit_config(30, 12, points=400, grids=(48, 48, 32), max_faces=1500, density_every=10,
                            eval_every=10, checkpoint_every=10, polish=polish)


def test_the_polish_moves_the_surfels_and_the_mesh_is_fused_after_it(tiny):
    base = fit(tiny, _config(0), progress=False)
    pol = fit(tiny, _config(10), progress=False)
    assert base.report["iterations"] == 42 and pol.report["iterations"] == 52
    assert any(not torch.equal(pol.surfels.params[k], base.surfels.params[k]) for k in base.surfels.params)
    # the final mesh is made last, from the polished surfels: not the mesh of the fit that stops at the loop's end
    assert len(pol.mesh.faces) and (len(pol.mesh.vertices) != len(base.mesh.vertices)
                                    or not np.array_equal(pol.mesh.vertices, base.mesh.vertices))
    stages = [r["stage"] for r in pol.history]
    assert stages[-1] == "final" and stages.count("final") == 1 and "polish" in stages
    k = stages.index("polish")
    assert set(stages[k:-1]) == {"polish"} and "coevolution" in stages[:k]
    assert "polish" not in [r["stage"] for r in base.history]
    last = pol.history[-1]
    assert last["iteration"] == 52
    # the report: the surfels' and the mesh's figures from the final evaluation, after the polish
    assert pol.report["psnr"] == last["psnr"] and pol.report["chamfer"] == last["chamfer"]
    # the polish trains on the photographs alone: no mesh term in its losses, which the co-evolution had
    coevo = next(r for r in pol.history if r["stage"] == "coevolution")
    polish = last  # its losses are those since the last evaluation (at 50): the polish's last iterations
    assert any(k.startswith("mesh_") for k in coevo["losses"])
    assert polish["losses"] and not any(k.startswith("mesh_") for k in polish["losses"])
    # nor a geometric regulariser: the photometric, mask and scale terms only
    assert {"normal", "distortion"} <= set(coevo["losses"])
    assert set(polish["losses"]) <= {"photo", "mask", "scale", "total"}
    assert pol.plan.polish_iterations == 10 and "polish_iterations" in pol.plan.overrides


def _same_mesh(a: trimesh.Trimesh, b: trimesh.Trimesh) -> None:
    """Two meshes fused from surfels that agree within RESUME_TOL: the same surface (vertex by vertex where the
    marching cubes made the same triangles, which float32 sums in the same order give here)."""
    assert abs(len(a.faces) - len(b.faces)) <= 0.01 * len(b.faces)
    if len(a.faces) == len(b.faces) and np.array_equal(a.faces, b.faces):
        np.testing.assert_allclose(a.vertices, b.vertices, rtol=0, atol=1e-4)
        if a.visual.kind == "vertex" and b.visual.kind == "vertex":  # colours of surfels equal within RESUME_TOL
            np.testing.assert_allclose(np.asarray(a.visual.vertex_colors, np.int32),
                                       np.asarray(b.visual.vertex_colors, np.int32), rtol=0, atol=2)
    else:  # a sign flip at a grid node moved a few triangles: the surfaces still agree
        assert abs(a.area - b.area) <= 0.01 * b.area


def test_a_fit_interrupted_in_its_polish_resumes_and_fuses_its_mesh_after_it(tiny, tmp_path):
    """An interrupted fit returns a mesh of the surfels it has; resumed, it finishes the polish and fuses the mesh
    the uninterrupted fit made (vertex colours too: an open mesh keeps the fusion's), with the same history."""
    def config():
        cfg = _config(10)
        cfg.final.watertight = False  # no Poisson re-mesh: the fused mesh with its colours is the result
        return cfg

    full = fit(tiny, config(), out_dir=tmp_path / "full", progress=False)
    assert full.mesh.visual.kind == "vertex"
    cfg = config()
    cfg.runtime.stop_at = 47
    part = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert part.report["status"] == "interrupted" and part.report["iterations"] == 47 and len(part.mesh.faces)
    assert part.history[-1]["stage"] == "final" and part.history[-1]["iteration"] == 47
    cfg.runtime.stop_at = None
    resumed = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert resumed.report["status"] == "completed" and resumed.report["iterations"] == 52
    for k, v in full.surfels.params.items():
        torch.testing.assert_close(resumed.surfels.params[k], v, atol=RESUME_TOL, rtol=RESUME_TOL)
    _same_mesh(resumed.mesh, full.mesh)
    assert resumed.mesh.visual.kind == "vertex"
    # the same surface: a few moved triangles change the sampled Chamfer by a few per cent at most
    assert resumed.report["chamfer"] == pytest.approx(full.report["chamfer"], rel=0.03)
    # the interrupted fit's final record is not in its checkpoint: the resumed history is the uninterrupted one's
    assert [(r["iteration"], r["stage"]) for r in resumed.history] == [(r["iteration"], r["stage"])
                                                                      for r in full.history]
    # a completed fit resumed again iterates no more, writes no checkpoint again, and fuses the same mesh
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "part" / "checkpoints").iterdir()}
    again = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert again.report["iterations"] == 52
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "part" / "checkpoints").iterdir()} == stamps
    _same_mesh(again.mesh, resumed.mesh)


def test_the_plan_polishes_only_after_a_proxy_mesh_loop(tiny):
    internal = tiny.normalized()
    cfg = FitConfig()
    cfg.warmup.iterations, cfg.coevolution.iterations = 30, 12
    p = make_plan(internal, cfg, torch.device("cpu"))
    assert p.mesh_loop and p.polish_iterations == 6
    cfg.coevolution.enabled = False
    assert make_plan(internal, cfg, torch.device("cpu")).polish_iterations == 0
    cfg.coevolution.enabled = None
    cfg.kind = SceneKind.SCENE  # no loop for scenes, so nothing to release the surfels from
    p = make_plan(internal, cfg, torch.device("cpu"))
    assert not p.mesh_loop and p.polish_iterations == 0
    assert "polish" in str(p) and "skipped" in str(p).split("polish", 1)[1].splitlines()[0]


def test_fit_surfels_does_not_polish(tiny, tmp_path):
    """A chunk's surfels are re-fused by the merge: they end as the mesh loop left them. Its checkpoints carry the
    configuration's own hash, so a directory that `fit` started resumes."""
    cfg = _config(10)
    cfg.runtime.stop_at = 20
    fit(tiny, cfg, out_dir=tmp_path, progress=False)
    cfg.runtime.stop_at = None
    res = fit_surfels(tiny, cfg, out_dir=tmp_path, progress=False)
    assert res.report["status"] == "completed" and res.report["iterations"] == 42 and res.plan.polish_iterations == 0
    assert len(res.mesh.faces) == 0 and any(e["event"] == "resumed" for e in res.report["events"])


def test_a_default_polish_keeps_the_hash_of_earlier_versions(monkeypatch):
    """Checkpoints written before the polish group existed resume: a configuration that leaves it to the plan hashes
    as one without the group did; one that sets it hashes apart."""
    from wtopo.fitting.config import config_hash

    cfg = FitConfig()
    cfg.runtime.seed = 3
    h = config_hash(cfg)
    to_dict = FitConfig.to_dict
    monkeypatch.setattr(FitConfig, "to_dict", lambda self: {k: v for k, v in to_dict(self).items() if k != "polish"})
    assert config_hash(cfg) == h
    monkeypatch.undo()
    cfg.polish.iterations = 5
    assert config_hash(cfg) != h
