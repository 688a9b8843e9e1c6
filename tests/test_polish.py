# SPDX-License-Identifier: Apache-2.0
"""The polish after the final mesh (``FitConfig.polish``): photometric iterations that move the surfels and their
held-out PSNR, never the mesh; resumable within it; planned only after a proxy-mesh loop."""

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


def test_the_polish_moves_the_surfels_and_keeps_the_mesh(tiny):
    base = fit(tiny, _config(0), progress=False)
    pol = fit(tiny, _config(10), progress=False)
    assert base.report["iterations"] == 42 and pol.report["iterations"] == 52
    # the mesh is made before the polish, from the same surfels
    np.testing.assert_array_equal(pol.mesh.faces, base.mesh.faces)
    np.testing.assert_array_equal(pol.mesh.vertices, base.mesh.vertices)
    assert any(not torch.equal(pol.surfels.params[k], base.surfels.params[k]) for k in base.surfels.params)
    stages = [r["stage"] for r in pol.history]
    k = stages.index("final")
    assert set(stages[k + 1:]) == {"polish"} and "polish" not in stages[:k] + [r["stage"] for r in base.history]
    final, last = pol.history[k], pol.history[-1]
    assert last["iteration"] == 52
    # the report: the surfels' figures after the polish, the mesh's from the final evaluation
    assert pol.report["psnr"] == last["psnr"] and pol.report["psnr"] != final["psnr"]
    assert pol.report["chamfer"] == final["chamfer"] == base.report["chamfer"] and "chamfer" not in last
    # the polish trains on the photographs alone: no mesh term in its losses, which the co-evolution had
    coevo = next(r for r in pol.history if r["stage"] == "coevolution")
    assert any(k.startswith("mesh_") for k in coevo["losses"])
    assert last["losses"] and not any(k.startswith("mesh_") for k in last["losses"])
    # nor a geometric regulariser: the photometric, mask and scale terms only
    assert {"normal", "distortion"} <= set(coevo["losses"])
    assert set(last["losses"]) <= {"photo", "mask", "scale", "total"}
    assert pol.plan.polish_iterations == 10 and "polish_iterations" in pol.plan.overrides


def test_a_fit_interrupted_in_its_polish_resumes_with_its_mesh(tiny, tmp_path):
    """The mesh made before the polish comes back from the checkpoint (vertex colours included: an open mesh
    keeps the fusion's), and the history is the uninterrupted one's."""
    def config():
        cfg = _config(10)
        cfg.final.watertight = False  # no Poisson re-mesh: the fused mesh with its colours is the result
        return cfg

    full = fit(tiny, config(), out_dir=tmp_path / "full", progress=False)
    assert full.mesh.visual.kind == "vertex"
    cfg = config()
    cfg.runtime.stop_at = 47
    part = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert part.report["status"] == "interrupted" and part.report["iterations"] == 47
    np.testing.assert_array_equal(part.mesh.faces, full.mesh.faces)  # the mesh was made at 42
    cfg.runtime.stop_at = None
    resumed = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert resumed.report["status"] == "completed" and resumed.report["iterations"] == 52
    np.testing.assert_array_equal(resumed.mesh.faces, full.mesh.faces)
    np.testing.assert_allclose(resumed.mesh.vertices, full.mesh.vertices, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(resumed.mesh.visual.vertex_colors, full.mesh.visual.vertex_colors)
    assert resumed.report["chamfer"] == full.report["chamfer"]
    assert [(r["iteration"], r["stage"]) for r in resumed.history] == [(r["iteration"], r["stage"])
                                                                      for r in full.history]
    for k, v in full.surfels.params.items():
        torch.testing.assert_close(resumed.surfels.params[k], v, atol=RESUME_TOL, rtol=RESUME_TOL)
    # a completed fit resumed again does nothing more and returns the same mesh
    again = fit(tiny, cfg, out_dir=tmp_path / "part", progress=False)
    assert again.report["iterations"] == 52
    np.testing.assert_array_equal(again.mesh.faces, full.mesh.faces)


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
