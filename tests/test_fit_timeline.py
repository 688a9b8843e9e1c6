# SPDX-License-Identifier: Apache-2.0
"""The fit's USD timeline (``runtime.usd_every``), written by a writer process: every sample lands, in order,
with the surfels and proxy mesh of its iteration in the caller's frame, and the final mesh is added; the writer's
errors reach the fit and a failed fit leaves no writer behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
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
    """The writer lags behind the fit: each sample still holds the surfels of the iteration it was taken at (on the
    CPU the host copy is the parameters' own memory, which the optimiser changes right after the hand-over)."""
    from pxr import Usd, UsdGeom

    from wtopo.fitting import _timeline

    taken = {}
    sample = _timeline.FitTimeline.sample

    def keep(self, it, surfels, proxy_mesh):
        taken[it] = self.sim.to_world(surfels.means.detach().cpu().double().numpy().copy())
        sample(self, it, surfels, proxy_mesh)

    monkeypatch.setattr(_timeline.FitTimeline, "sample", keep)
    cfg = small_fit_config(30, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=100, eval_every=0)
    cfg.runtime.usd_every = 3
    wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    stage = Usd.Stage.Open(str(tmp_path / "run" / "timeline.usdc"))
    attr = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Surfels")).GetPositionsAttr()
    assert sorted(taken) == list(range(3, 31, 3))
    for it, means in taken.items():
        np.testing.assert_allclose(np.asarray(attr.Get(float(it))), means, rtol=0, atol=1e-5, err_msg=str(it))


def _child_text(exc: BaseException) -> str:
    """The child's traceback that came back with ``exc`` (a note; on Python 3.10 the cause's message)."""
    return "".join(getattr(exc, "__notes__", [])) or str(exc.__cause__ or "")


def test_a_writer_that_dies_stops_the_timeline_not_the_fit(tmp_path, monkeypatch):
    from wtopo.fitting import _timeline

    writers = []
    sample = _timeline.FitTimeline.sample

    def kill_at_ten(self, it, surfels, proxy_mesh):
        if self.writer is not None:
            writers.append(self.writer)
        if it == 10:
            self.writer._proc.kill()
            self.writer._proc.wait()
        sample(self, it, surfels, proxy_mesh)

    monkeypatch.setattr(_timeline.FitTimeline, "sample", kill_at_ten)
    cfg = small_fit_config(20, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)
    cfg.runtime.usd_every = 5
    with pytest.warns(RuntimeWarning, match="timeline stopped .*SIGKILL"):
        res = wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    assert writers and writers[-1]._proc.poll() is not None
    assert not (tmp_path / "run" / "timeline.usdc").exists() and (tmp_path / "run" / "mesh.ply").exists()
    failed = [e for e in res.report["events"] if e["event"] == "timeline_failed"]
    assert len(failed) == 1 and "iteration 10" in failed[0]["error"]


def test_the_writers_error_stops_the_timeline_and_a_failed_fit_ends_the_writer(tmp_path, monkeypatch):
    from wtopo.fitting import _timeline

    # the file's place is taken by a folder: the writer's atomic rename fails at the end, in the child
    (tmp_path / "run" / "timeline.usdc").mkdir(parents=True)
    cfg = small_fit_config(10, 0, points=400, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)
    cfg.runtime.usd_every = 5
    with pytest.warns(RuntimeWarning, match="timeline stopped .* at the end"):
        res = wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run", progress=False)
    assert res.mesh is not None and (tmp_path / "run" / "mesh.ply").exists()
    assert [e for e in res.report["events"] if e["event"] == "timeline_failed"]

    # a fit that fails for its own reasons ends its writer and raises its own error
    writers = []
    sample = _timeline.FitTimeline.sample

    def fail(self, it, surfels, proxy_mesh):
        writers.append(self.writer)
        sample(self, it, surfels, proxy_mesh)
        raise KeyError("the fit's own error")

    monkeypatch.setattr(_timeline.FitTimeline, "sample", fail)
    with pytest.raises(KeyError, match="own error"):
        wtopo.fit(_scene(), cfg, out_dir=tmp_path / "run2", progress=False)
    assert writers and writers[0]._proc.poll() is not None
    assert not (tmp_path / "run2" / "timeline.usdc").exists()


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
    tl = FitTimeline(tmp_path / "fit.usdc", 1, sim, cams, Timers(), max_surfels=7)
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


def test_the_writer_process_makes_the_writers_calls_and_raises_its_errors(tmp_path):
    from wtopo.io import TimelineWriter
    from wtopo.io._timeline_process import TimelineProcess

    g = np.random.default_rng(0)
    arrays = [{"means": g.random((30, 3)), "quats": g.standard_normal((30, 4)), "scales": g.random((30, 2)) * 0.1,
               "opacities": g.random(30), "colors_or_sh": g.random((30, 3))} for _ in range(3)]
    verts, faces = g.random((4, 3)), np.array([[0, 1, 2], [0, 2, 3]])
    proc, ref = TimelineProcess(tmp_path / "a.usdc", max_surfels=20), TimelineWriter(tmp_path / "b.usdc",
                                                                                      max_surfels=20)
    for w in (proc, ref):
        for it, a in enumerate(arrays, 1):
            w.add_sample(it * 10, mesh_verts=verts * it, mesh_faces=faces, **a)
        w.add_mesh("final", verts, faces)
    stats, want = proc.close(), ref.close()
    assert (stats.samples, stats.bytes) == (want.samples, want.bytes)
    a, b = read_timeline(tmp_path / "a.usdc"), read_timeline(tmp_path / "b.usdc")
    assert a.iterations == b.iterations == [10, 20, 30]
    for sa, sb in zip(a.samples, b.samples, strict=True):
        np.testing.assert_array_equal(sa.verts, sb.verts)
        assert sa.num_surfels == sb.num_surfels == 20

    # an argument error surfaces at the next call or at close, with the child's traceback; nothing is written
    bad = TimelineProcess(tmp_path / "c.usdc")
    bad.add_sample(5, means=arrays[0]["means"])  # the writer wants every surfel array together
    with pytest.raises(ValueError, match="given together") as info:
        bad.close()
    assert "add_sample" in _child_text(info.value)
    assert not (tmp_path / "c.usdc").exists()
    # abort ends the child and writes nothing
    gone = TimelineProcess(tmp_path / "d.usdc")
    gone.add_sample(1, **arrays[0])
    gone.abort()
    assert gone._proc.poll() is not None and not (tmp_path / "d.usdc").exists()
    with pytest.raises(RuntimeError, match="closed"):
        gone.add_sample(2, **arrays[1])


def test_a_writer_that_cannot_start_says_how_to_fit_without_a_timeline(tmp_path, monkeypatch):
    from wtopo.io._timeline_process import TimelineProcess, TimelineWriterError

    monkeypatch.setattr("sys.executable", str(tmp_path / "no-python-here"))
    with pytest.raises(TimelineWriterError, match="usd_every=0"):
        TimelineProcess(tmp_path / "a.usdc")


def test_the_writer_process_survives_prints_and_a_caller_that_goes_away(tmp_path, monkeypatch):
    """Whatever the child prints (a site hook, an import's greeting) does not count as an answer; a caller that dies
    without closing leaves neither the file nor the call folder."""
    from wtopo.io._timeline_process import TimelineProcess

    hook = tmp_path / "site"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text("print('hello from a site hook')\nprint('and another line')\n")
    monkeypatch.setenv("PYTHONPATH", str(hook) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    g = np.random.default_rng(1)
    a = {"means": g.random((8, 3)), "quats": g.standard_normal((8, 4)), "scales": g.random((8, 2)) * 0.1,
         "opacities": g.random(8), "colors_or_sh": g.random((8, 3))}
    p = TimelineProcess(tmp_path / "a.usdc")
    p.add_sample(1, **dict(a, means=a["means"] + 1))
    # nothing is unanswered only once the child has made both calls (the hook's lines are no answers)
    deadline = time.monotonic() + 60
    while p._pending.unanswered and time.monotonic() < deadline:
        time.sleep(0.005)
    assert p._pending.unanswered == 0 and not [f for f in os.listdir(p._dir) if f.endswith(".call")]
    for it in (2, 3):
        p.add_sample(it, **dict(a, means=a["means"] + it))  # a sample equal to the last is not authored again
    assert p.close().samples == 3
    assert read_timeline(tmp_path / "a.usdc").iterations == [1, 2, 3]

    gone = TimelineProcess(tmp_path / "b.usdc")
    gone.add_sample(1, **a)
    folder = gone._dir
    gone._proc.stdin.close()  # the caller's end of the pipe goes, as when its process dies
    gone._proc.wait(timeout=60)
    assert not os.path.exists(folder) and not (tmp_path / "b.usdc").exists()
    gone.abort()


class TwoArgError(Exception):
    """An exception that pickles but does not rebuild (its ``__init__`` takes two arguments)."""

    def __init__(self, what, code):
        super().__init__(f"{what}: {code}")


class Bomb:
    """Raises :class:`TwoArgError` when the writer in the child reads it as an array."""

    def __array__(self, *args, **kwargs):
        raise TwoArgError("bomb", 7)


def test_an_error_that_does_not_rebuild_comes_back_as_its_text(tmp_path):
    from wtopo.io._timeline_process import TimelineProcess, TimelineWriterError

    p = TimelineProcess(tmp_path / "a.usdc")
    p.add_mesh("final", Bomb(), np.zeros((1, 3), dtype=np.int64))
    with pytest.raises(TimelineWriterError, match="TwoArgError: bomb: 7"):
        p.close()


def test_a_dead_child_frees_a_waiting_caller(tmp_path, monkeypatch):
    from wtopo.io import _timeline_process
    from wtopo.io._timeline_process import TimelineProcess, TimelineWriterError

    monkeypatch.setattr(_timeline_process, "_UNANSWERED_BYTES", -1)  # every call waits for the one before
    p = TimelineProcess(tmp_path / "a.usdc")
    p._proc.send_signal(signal.SIGSTOP)  # the child takes no call
    killer = threading.Timer(1.0, p._proc.kill)
    killer.start()
    t0 = time.monotonic()
    with pytest.raises(TimelineWriterError, match="SIGKILL"):
        p.add_mesh("a", np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert time.monotonic() - t0 < 30
    killer.join()


def test_a_caller_killed_mid_fit_leaves_no_files(tmp_path):
    """The caller's process dies (SIGKILL, the OOM killer): the child removes the calls it was handed."""
    script = tmp_path / "caller.py"
    script.write_text(
        "import os, signal, sys, time\n"
        "import numpy as np\n"
        "from wtopo.io._timeline_process import TimelineProcess\n"
        f"p = TimelineProcess({str(tmp_path / 'a.usdc')!r})\n"
        "for it in range(1, 6):\n"
        "    p.add_mesh(f'm{it}', np.random.rand(1000, 3), np.zeros((10, 3), dtype=np.int64))\n"
        "print(p._dir, flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                         cwd=str(Path(__file__).parent.parent))
    folder = out.stdout.strip()
    assert folder.startswith(tempfile.gettempdir()), (out.stdout, out.stderr)
    deadline = time.monotonic() + 60
    while os.path.exists(folder) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not os.path.exists(folder) and not (tmp_path / "a.usdc").exists()
