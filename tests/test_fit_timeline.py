# SPDX-License-Identifier: Apache-2.0
"""The fit's USD timeline (``runtime.usd_every``), written on a worker thread: every sample lands, in order,
with the surfels and proxy mesh of its iteration in the caller's frame, and the final mesh is added."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

pytest.importorskip("pxr")

sys.path.insert(0, str(Path(__file__).parent))
from fit_configs import small_fit_config  # noqa: E402

import wtopo  # noqa: E402
from wtopo import scenes  # noqa: E402
from wtopo.io import read_timeline  # noqa: E402
from wtopo.scene import Similarity  # noqa: E402


def _scene():
    return scenes.from_mesh(trimesh.creation.icosphere(subdivisions=3), n_views=8, resolution=32, texture="coffee",
                            seed=0)


def test_fit_writes_every_sample_in_the_callers_frame(tmp_path):
    from pxr import Usd, UsdGeom

    cfg = small_fit_config(20, 20, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)
    cfg.runtime.usd_every = 5
    res = wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    path = tmp_path / "run" / "timeline.usdc"
    tl = read_timeline(path)
    assert tl.iterations == list(range(5, 41, 5))
    # the proxy mesh appears once the co-evolution has one, and the final mesh is the result's (caller's frame)
    assert all(len(s.faces) == 0 for s in tl.samples if s.iteration <= 20)
    assert all(len(s.faces) > 0 for s in tl.samples if s.iteration > 20)
    v, f = tl.meshes["final"]
    np.testing.assert_array_equal(f, res.mesh.faces)
    np.testing.assert_allclose(v, res.mesh.vertices, rtol=0, atol=1e-5)
    # the last sample holds the fitted surfels (no polish here), mapped back to the caller's frame
    assert tl.samples[-1].num_surfels == len(res.surfels)
    sim = Similarity(**res.report["normalization"])
    stage = Usd.Stage.Open(str(path))
    pos = np.asarray(UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Surfels")).GetPositionsAttr().Get(40.0))
    np.testing.assert_allclose(pos, sim.to_world(res.surfels.means.detach().cpu().double().numpy()), rtol=0,
                               atol=1e-5)


def test_each_sample_holds_its_iterations_surfels_while_the_fit_goes_on(tmp_path, monkeypatch):
    """A slow writer lags behind the fit: each sample still holds the surfels of the iteration it was taken at (the
    host copy is the fit's own, never the parameters the optimiser keeps changing)."""
    from pxr import Usd, UsdGeom

    from wtopo.fitting import _timeline

    taken = {}
    sample, write = _timeline.FitTimeline.sample, _timeline.FitTimeline._write

    def keep(self, it, surfels, proxy_mesh):
        taken[it] = self.sim.to_world(surfels.means.detach().cpu().double().numpy().copy())
        sample(self, it, surfels, proxy_mesh)

    def slow(self, it, host):
        time.sleep(0.1)  # the fit runs several iterations before the worker reads the sample
        write(self, it, host)

    monkeypatch.setattr(_timeline.FitTimeline, "sample", keep)
    monkeypatch.setattr(_timeline.FitTimeline, "_write", slow)
    cfg = small_fit_config(30, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=100, eval_every=0)
    cfg.runtime.usd_every = 3
    wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    stage = Usd.Stage.Open(str(tmp_path / "run" / "timeline.usdc"))
    attr = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Surfels")).GetPositionsAttr()
    assert sorted(taken) == list(range(3, 31, 3))
    for it, means in taken.items():
        np.testing.assert_allclose(np.asarray(attr.Get(float(it))), means, rtol=0, atol=1e-5, err_msg=str(it))


def test_a_failed_sample_is_raised_by_the_fit(tmp_path, monkeypatch):
    from wtopo.io import TimelineWriter

    def broken(self, iteration, **kw):
        raise OSError("disk full")

    monkeypatch.setattr(TimelineWriter, "add_sample", broken)
    cfg = small_fit_config(20, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)
    cfg.runtime.usd_every = 5
    with pytest.raises(OSError, match="disk full"):
        wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    # the failed fit stopped its writer's thread
    assert not [t for t in threading.enumerate() if t.name.startswith("wtopo-timeline")]


def test_samples_leave_the_device_as_the_writer_keeps_them(tmp_path):
    """Above the writer's surfel budget the fit sends the writer's own strided subset, and only the SH's DC term:
    the file is the one the writer makes of the whole arrays."""
    from pxr import Usd, UsdGeom

    from wtopo.fitting._timeline import FitTimeline
    from wtopo.fitting.profiling import Timers
    from wtopo.io import TimelineWriter

    g = torch.Generator().manual_seed(0)
    n = 20
    s = SimpleNamespace(means=torch.rand(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                        scales=torch.rand(n, 2, generator=g) * 0.1, opacities=torch.rand(n, generator=g),
                        sh=torch.randn(n, 16, 3, generator=g) * 0.2)
    sim = Similarity(2.0, (0.1, -0.2, 0.3))
    cams = _scene().cameras[:2]
    tl = FitTimeline(tmp_path / "fit.usdc", 1, sim, cams, Timers())
    tl.writer.max_surfels = 7
    tl.sample(1, s, None)
    tl.close(None)
    ref = TimelineWriter(tmp_path / "ref.usdc", max_surfels=7)
    ref.add_cameras([sim.to_world(c) for c in cams])
    ref.add_sample(1, means=sim.to_world(s.means.double().numpy()), quats=s.quats.numpy(),
                   scales=sim.length_to_world(s.scales.double().numpy()), opacities=s.opacities.numpy(),
                   colors_or_sh=s.sh.numpy())
    ref.close()
    a, b = (Usd.Stage.Open(str(tmp_path / f)) for f in ("fit.usdc", "ref.usdc"))
    positions = UsdGeom.PointInstancer(a.GetPrimAtPath("/World/Surfels")).GetPositionsAttr().Get(1.0)
    assert len(positions) == 7
    compared = 0
    for prim in a.Traverse():  # every sampled attribute of every prim (the instancer's, the splats' when written)
        for attr in prim.GetAttributes():
            if attr.GetNumTimeSamples() == 0:
                continue
            other = b.GetPrimAtPath(prim.GetPath()).GetAttribute(attr.GetName())
            np.testing.assert_allclose(np.asarray(attr.Get(1.0), dtype=np.float64),
                                       np.asarray(other.Get(1.0), dtype=np.float64), rtol=1e-6, atol=1e-7,
                                       err_msg=str(attr.GetPath()))
            compared += 1
    assert compared >= 8
