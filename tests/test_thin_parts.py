# SPDX-License-Identifier: Apache-2.0
"""The proxy's thickness along the pixel rays (analytic slab and sphere) and the co-evolution's thin-part
rule: its share, its decision, the fit's event and a resumed fit keeping the decision."""

import numpy as np
import pytest
import torch
import trimesh
from test_fit import _config, tiny  # noqa: F401  (the fixture)

from wtopo import Camera
from wtopo.fitting.config import MeshConfig
from wtopo.fitting.proxy import ProxyMesh, ProxyResult
from wtopo.fitting.thin_parts import thin_cells, thin_parts


def _down_z(width=24, height=20):
    """A camera at (0.5, 0.5, -1) in the unit cube's frame looking along +z (identity rotation)."""
    w2c = np.eye(4)
    w2c[:3, 3] = [-0.5, -0.5, 1.0]
    return Camera(np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]]), w2c, width, height)


def _result(mesh: trimesh.Trimesh) -> ProxyResult:
    return ProxyResult(torch.as_tensor(mesh.vertices, dtype=torch.float64),
                       torch.as_tensor(mesh.faces, dtype=torch.int32))


def test_slab_thickness_is_its_depth_in_cells():
    """A slab 0.05 thick across the view, wider than it: every pixel reads its chord through the slab,
    0.05 / cell (3.2 cells at 64^3, the unit box) times the ray's length per unit of depth (1 / cos of its
    angle to the axis); the exit ray starts just past the entry, so the entry face is not the exit."""
    proxy = ProxyMesh(MeshConfig(resolution=64))
    slab = trimesh.creation.box(extents=(3.0, 3.0, 0.05))
    slab.apply_translation((0.5, 0.5, 0.5))
    cam = _down_z()
    render, cells = proxy.thickness(_result(slab), cam)
    assert bool(render.mask.all()), "the slab fills the view"
    assert cells.dtype == torch.float64 and cells.shape == (20, 24)
    _, d = cam.pixel_rays("cpu", torch.float64)
    assert torch.allclose(cells, 0.05 * 64 * d.norm(dim=-1), rtol=1e-6, atol=1e-6)


def test_sphere_thickness_is_its_chord_and_misses_are_inf():
    """An icosphere of radius 0.3: the centre pixel crosses the diameter (38.4 cells at 64^3, within the
    facets' sag), pixels off the sphere are inf, and the chord falls towards the rim."""
    proxy = ProxyMesh(MeshConfig(resolution=64))
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    ball.apply_translation((0.5, 0.5, 0.5))
    cam = _down_z(41, 41)
    render, cells = proxy.thickness(_result(ball), cam)
    assert 0.5 * 64 * 0.6 * 0.99 < float(cells[20, 20]) < 0.6 * 64 * 1.001
    assert bool(torch.isinf(cells[~render.mask]).all()) and bool((~render.mask).any())
    row = cells[20][render.mask[20]]
    assert float(row[0]) < float(cells[20, 20]) and float(row[-1]) < float(cells[20, 20])


def test_rule_refines_the_grid_then_turns_the_mesh_terms_off(tiny):  # noqa: F811
    """The share is measured once at the co-evolution's start. At or below ``losses.mesh_thin_limit`` the
    plan's grid and the mesh terms stay. Above it the grid doubles and is measured again; still above it
    (or no finer grid allowed), the mesh terms stay off (no proxy built by the objective, no mesh term).
    The fit records the decision; no co-evolution or no mesh term: nothing measured."""
    from wtopo.fitting.loop import FitRun
    from wtopo.fitting.stages import Stage
    from wtopo.fitting.thin_parts import MAX_RESOLUTION

    runs = {}
    for limit in (0.0, 1.0):
        cfg = _config(10, 8)  # a 32^3 proxy
        cfg.coevolution.enabled = True
        cfg.losses.mesh_thin_limit = limit
        run = FitRun(tiny, cfg, None, progress=False)
        run._start()
        run._thin_parts()
        runs[limit] = run
    off, on = runs[0.0].coevolution_info, runs[1.0].coevolution_info
    assert 0.0 < on["thin_share"] <= 1.0, "a 10-iteration warm-up leaves thin, double-walled parts"
    assert on["mesh_terms"] is True and on["resolution"] == 32 and "coarse" not in on
    assert runs[1.0].proxy.cfg.resolution == 32
    assert off["coarse"] == {"resolution": 32, "thin_share": on["thin_share"]}
    assert off["resolution"] == 64 and runs[0.0].proxy.cfg.resolution == 64, "the grid doubles first"
    assert off["thin_share"] > 0.0 and off["mesh_terms"] is False
    assert [e for e in runs[0.0].events if e["event"] == "thin_parts"][0]["mesh_terms"] is False
    t_off = runs[0.0].objective(Stage.COEVOLUTION, 12, 0, runs[0.0].surfels, runs[0.0].proxy)
    t_on = runs[1.0].objective(Stage.COEVOLUTION, 12, 0, runs[1.0].surfels, runs[1.0].proxy)
    assert not t_off.proxy_built and "mesh_depth" not in t_off.losses
    assert t_on.proxy_built and "mesh_depth" in t_on.losses
    run = runs[1.0]
    fine = run.proxy.with_resolution(MAX_RESOLUTION)
    cfg = run.cfg
    cfg.losses.mesh_thin_limit = 0.0
    top = thin_parts(fine, run.surfels, run.train.cameras, cfg)  # no finer grid: off at once
    assert top["resolution"] == MAX_RESOLUTION and "coarse" not in top and top["mesh_terms"] is False
    cfg = _config(10, 8)
    cfg.coevolution.enabled = False
    run = FitRun(tiny, cfg, None, progress=False)
    run._start()
    assert thin_parts(run.proxy, run.surfels, run.train.cameras, run.cfg) == {}


def test_refined_grid_resolves_a_thin_slab():
    """A slab 2.5 cells thick at 64^3 (all of it thin) is 5 cells thick on the doubled grid: the share
    the rule re-measures there is 0."""
    from wtopo.fitting.config import FitConfig

    proxy = ProxyMesh(MeshConfig(resolution=64))
    slab = trimesh.creation.box(extents=(3.0, 3.0, 2.5 / 64))
    slab.apply_translation((0.5, 0.5, 0.5))
    cam = _down_z()
    limit = thin_cells(FitConfig())
    assert limit == 3.0  # at the default sigma of 1
    _, coarse = proxy.thickness(_result(slab), cam)
    _, fine = proxy.with_resolution(128).thickness(_result(slab), cam)
    assert bool((coarse < limit).all()) and not bool((fine < limit).any())


def test_resumed_fit_keeps_the_decision(tiny, tmp_path):  # noqa: F811
    """A fit stopped in the co-evolution resumes with the decision its checkpoint holds (the surfels
    have moved since, so measuring again could decide otherwise), and reports it."""
    from wtopo import fit

    cfg = _config(10, 8)
    cfg.coevolution.enabled = True
    cfg.losses.mesh_thin_limit = 0.0
    cfg.runtime.checkpoint_every = 2
    cfg.runtime.stop_at = 14
    first = fit(tiny, cfg, out_dir=tmp_path, progress=False)
    assert first.report["coevolution"]["mesh_terms"] is False and first.report["coevolution"]["resolution"] == 64
    cfg.runtime.stop_at = None
    cfg.losses.mesh_thin_limit = 0.0
    res = fit(tiny, cfg, out_dir=tmp_path, progress=False)
    assert res.report["status"] == "completed" and res.report["coevolution"] == first.report["coevolution"]
    assert sum(e["event"] == "thin_parts" for e in res.report["events"]) == 1, "measured once, before the stop"


@pytest.mark.slow
def test_the_thin_decay_acts_only_where_the_rule_refined_the_grid(tiny, monkeypatch):  # noqa: F811
    """The thin decay (:data:`wtopo.fitting.schedule.THIN_DECAY`) changes a fit whose proxy grid the thin-part
    rule refined (the surfels move less in the co-evolution) and leaves a fit where the rule did not fire
    exactly as it was."""
    from wtopo import fit
    from wtopo.fitting import loop, schedule

    def run(limit, thin_decay):
        cfg = _config(10, 8)
        cfg.coevolution.enabled = True
        cfg.losses.mesh_thin_limit = limit
        monkeypatch.setattr(loop, "means_rate", lambda *a, **k: schedule.means_rate(*a, **k, thin_decay=thin_decay))
        res = fit(tiny, cfg, progress=False)
        return res.surfels.means.detach().clone(), res.report["coevolution"]

    fired, info = run(0.0, 0.0)
    assert "coarse" in info, "the rule refined the grid"
    slowed, _ = run(0.0, 0.5)
    assert not torch.equal(fired, slowed)
    quiet, info = run(1.0, 0.0)
    assert "coarse" not in info and info["mesh_terms"] is True
    assert torch.equal(quiet, run(1.0, 0.5)[0])



def test_the_final_mesh_hears_whether_the_object_was_too_thin_for_the_mesh_terms(tiny):  # noqa: F811
    """The outline offset (wtopo/geometry/outline.py) moves a masked object's final mesh onto the masks; where the
    thin-part rule turned the mesh terms off it may only move inward (tests/test_outline.py has that rule)."""
    from unittest import mock

    from wtopo.fitting import _final_mesh
    from wtopo.fitting.loop import FitRun

    for limit, thin in ((0.0, True), (1.0, False)):
        cfg = _config(10, 8)
        cfg.coevolution.enabled = True
        cfg.losses.mesh_thin_limit = limit
        run = FitRun(tiny, cfg, None, progress=False)
        run._start()
        run._thin_parts()
        with mock.patch.object(_final_mesh, "_outline", wraps=_final_mesh._outline) as spy:
            run._final_mesh()
        assert spy.call_args.kwargs["thin"] is thin
        (ev,) = [e for e in run.events if e["event"] == "outline_offset"]
        assert ev["views"] > 0 and ("skipped" in ev) == (thin and ev["pixels"] > 0), ev
