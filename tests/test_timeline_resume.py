# SPDX-License-Identifier: Apache-2.0
"""A resumed fit keeps its earlier run's USD timeline: the writer authors the earlier file's samples up to the
resume's iteration before its own (``earlier_samples``, ``TimelineProcess.carry_over``), so that ``timeline.usdc``
holds the whole fit, the earlier samples as they were written."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

pytest.importorskip("pxr")

sys.path.insert(0, str(Path(__file__).parent))
from fit_configs import small_fit_config  # noqa: E402

import wtopo  # noqa: E402
from wtopo import scenes  # noqa: E402
from wtopo.io import TimelineWriter, read_timeline  # noqa: E402
from wtopo.io._timeline_process import TimelineProcess  # noqa: E402
from wtopo.io._usd_read import earlier_samples  # noqa: E402


def _sampled(path, until=None) -> dict:
    """Every time-sampled attribute's value at each of its sample times (up to ``until``), by (path, time)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            for t in attr.GetTimeSamples():
                if until is None or t <= until:
                    out[(str(attr.GetPath()), t)] = np.asarray(attr.Get(t), dtype=np.float64)
    return out


def _assert_same_samples(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k, v in a.items():
        np.testing.assert_allclose(b[k], v, rtol=1e-6, atol=1e-7, err_msg=str(k))


def _write(path, arrays, mesh_from: int):
    w = TimelineWriter(path, max_surfels=20)
    g = np.random.default_rng(1)
    verts, faces = g.random((5, 3)), np.array([[0, 1, 2], [0, 2, 3], [1, 3, 4]])
    for it, a in enumerate(arrays, 1):
        mesh = {"mesh_verts": verts * it, "mesh_faces": faces} if it >= mesh_from else {}
        w.add_sample(it * 10, **mesh, **a)
    w.add_mesh("final", verts, faces)
    w.close()


def test_the_writer_process_carries_an_earlier_files_samples_over(tmp_path):
    """A new writer with carry_over(path, 30) holds the earlier file's samples at 10, 20 and 30 as they were (the
    proxy mesh from its first sample on), then its own; the earlier file's later samples and static meshes stay
    out. The file carried over may be the one the new writer replaces."""
    g = np.random.default_rng(0)
    arrays = [{"means": g.random((30, 3)), "quats": g.standard_normal((30, 4)), "scales": g.random((30, 2)) * 0.1,
               "opacities": g.random(30), "colors_or_sh": g.random((30, 1, 3)) - 0.5} for _ in range(5)]
    path = tmp_path / "timeline.usdc"
    _write(path, arrays, mesh_from=2)
    shutil.copy(path, tmp_path / "earlier.usdc")
    assert [it for it, _ in earlier_samples(path, 30)] == [10, 20, 30]
    proc = TimelineProcess(path, max_surfels=20)
    proc.carry_over(path, 30)
    proc.add_sample(40, **arrays[0])
    proc.close()
    tl = read_timeline(path)
    assert tl.iterations == [10, 20, 30, 40] and "final" not in tl.meshes
    assert len(tl.samples[0].faces) == 0 and all(len(s.faces) == 3 for s in tl.samples[1:])
    _assert_same_samples(_sampled(tmp_path / "earlier.usdc", until=30), _sampled(path, until=30))


def test_a_resumed_fit_keeps_the_earlier_runs_samples(tmp_path):
    """Stopped at 25 and resumed: the timeline holds every sample of the fit, those up to 25 as the first run
    wrote them."""
    scene = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=3), n_views=8, resolution=32,
                             texture="coffee", seed=0)
    cfg = small_fit_config(20, 20, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)
    cfg.runtime.usd_every = 5
    cfg.runtime.stop_at = 25
    run = tmp_path / "run"
    wtopo.fit(scene, cfg, out_dir=run, progress=False)
    assert read_timeline(run / "timeline.usdc").iterations == [5, 10, 15, 20, 25]
    shutil.copy(run / "timeline.usdc", tmp_path / "first.usdc")
    cfg.runtime.stop_at = None
    res = wtopo.fit(scene, cfg, out_dir=run, progress=False)
    assert res.report["status"] == "completed"
    tl = read_timeline(run / "timeline.usdc")
    assert tl.iterations == list(range(5, 41, 5)) and "final" in tl.meshes
    assert all(len(s.faces) > 0 for s in tl.samples if s.iteration > 20)
    _assert_same_samples(_sampled(tmp_path / "first.usdc", until=25), _sampled(run / "timeline.usdc", until=25))
