# SPDX-License-Identifier: Apache-2.0
"""``runtime.profile`` / ``wtopo fit --profile``: the per-stage time table of a fit (wtopo.fitting.profiling)."""

import json
import time

import pytest
import torch
import trimesh
from fit_configs import small_fit_config

from wtopo import scenes
from wtopo._profile import section
from wtopo.fitting import fit
from wtopo.fitting.loop import FitRun
from wtopo.fitting.profiling import Timers, format_profile

# what a user needs to see (issue 16): every stage of the loop and the proxy mesh's parts, as call paths
_PATHS = {
    "setup", "init", "init/init_seed", "init/init_setup", "render", "render/rasterize_forward", "losses", "read",
    "backward", "optimizer", "statistics", "densify",
    "proxy",
    "proxy/oriented_points", "proxy/poisson", "proxy/poisson/scatter", "proxy/marching_cubes", "raycast",
    "raycast/bvh_build", "tsdf", "tsdf/render_depths", "tsdf/tsdf_fusion", "tsdf/tsdf_fusion/tsdf_integrate",
    "tsdf/tsdf_fusion/marching_cubes", "final", "final/tsdf_fusion", "evaluate", "checkpoint", "outputs", "release",
}


@pytest.fixture(scope="module")
def tiny():
    """A textured sphere, 8 views of 24 px, masks."""
    return scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24, rig="sphere",
                            texture="coffee", name="tiny")


def test_sections_sync_and_record_call_paths():
    """Call sync at each section's start and end only when given; record self and total time per call path."""
    calls = []
    t = Timers(lambda: calls.append(1))
    with t("outer"):
        with section("inner"):
            pass
        with section("inner"):
            pass
    assert len(calls) == 6  # outer + two inner sections, start and end each
    assert t.paths[("outer", "inner")][2] == 2 and t.paths[("outer",)][2] == 1
    outer_total, outer_self, _ = t.paths[("outer",)]
    assert outer_total >= outer_self + t.paths[("outer", "inner")][0] - 1e-9
    quiet = Timers()
    with quiet("outer"), section("inner"):
        pass
    assert quiet.sync is None and set(quiet.paths) == {("outer",), ("outer", "inner")}
    p = t.profile(wall=1.0)
    assert [r["path"] for r in p["rows"]] == ["outer", "outer/inner"] and p["synchronized"]
    assert "outer" in format_profile(p) and "inner" in format_profile(p)


def test_a_section_left_by_an_exception_is_recorded_and_closed():
    """An exception inside nested sections still records both, and no collector stays open after it."""
    from wtopo._profile import in_section

    t = Timers()
    with pytest.raises(KeyError), t("outer"), section("inner"):
        raise KeyError("x")
    assert not in_section()
    assert t.paths[("outer", "inner")][2] == 1 and t.paths[("outer",)][2] == 1
    with section("alone"):  # no collector: times nothing
        assert not in_section()
    with t("again"):
        assert in_section()
    assert set(t.paths) == {("outer",), ("outer", "inner"), ("again",)}


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_only_a_profiled_cuda_fit_synchronises(tiny, device):
    """Synchronise the sections of a fit only with runtime.profile on CUDA (never otherwise)."""
    for profile in (False, True):
        cfg = small_fit_config(0, 0, points=50, grids=(16, 16, 16), max_faces=100, density_every=10, eval_every=0)
        cfg.runtime.device, cfg.runtime.profile = device, profile
        run = FitRun(tiny, cfg, None, progress=False)
        assert (run.timers.sync is not None) == (profile and device.startswith("cuda")), (device, profile)


@pytest.mark.slow
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs CUDA"))])
def test_profiled_fit_reports_every_stage_within_the_wall_time(tiny, tmp_path, capsys, device, monkeypatch):
    """Print and store the stage table of a tiny fit: every stage, calls, sums within the wall time."""
    from wtopo.fitting import _strategy as strategy

    cfg = small_fit_config(24, 8, points=300, grids=(32, 40, 32), max_faces=800, density_every=8, eval_every=16,
                           checkpoint_every=16)
    monkeypatch.setattr(strategy, "DENSIFY_START", 0.0)
    cfg.runtime.profile = True
    cfg.runtime.device = device
    res = fit(tiny, cfg, out_dir=tmp_path, progress=False)
    prof = res.report["profile"]
    rows = {r["path"]: r for r in prof["rows"]}
    assert not _PATHS - set(rows), sorted(_PATHS - set(rows))
    assert rows["backward"]["calls"] == 32 and rows["render"]["calls"] >= 32  # + the evaluation's renders
    from wtopo.fitting.presets import budget

    every = budget(cfg.preset, device).mesh_every  # the proxy is built on every mesh_every-th co-evolution iteration
    assert rows["proxy"]["calls"] == len(range(0, 8, every)) and rows["tsdf"]["calls"] == 1
    for r in prof["rows"]:
        assert r["total_s"] >= r["self_s"] >= 0 and r["calls"] > 0, r
        kids = [k for k in prof["rows"] if k["path"].rsplit("/", 1)[0] == r["path"] and k is not r]
        assert sum(k["total_s"] for k in kids) <= r["total_s"] - r["self_s"] + 1e-3, r["path"]
    tops = [r for r in prof["rows"] if r["depth"] == 0]
    assert abs(sum(r["total_s"] for r in tops) - prof["sections_s"]) < 1e-2
    assert 0 < prof["sections_s"] <= prof["wall_s"]
    assert sum(r["percent_wall"] for r in tops) <= 100.0 + 1e-6
    assert prof["synchronized"] is device.startswith("cuda")  # the CPU has nothing to synchronise
    out = capsys.readouterr().out
    for label in ("wtopo fit profile", "setup (plan", "render forward", "backward", "losses", "host read",
                  "optimizer", "density statistics", "last good state (copy)", "freeing the step's buffers",
                  "density control",
                  "proxy mesh", "marching cubes", "BVH build", "TSDF re-initialisation", "TSDF fusion",
                  "evaluation", "checkpoint", "report and output files", "outside any section"):
        assert label in out, label
    assert json.loads((tmp_path / "report.json").read_text())["profile"]["rows"] == prof["rows"]
    assert "profile" not in fit(tiny, small_fit_config(4, 0, points=100, grids=(16, 16, 16), max_faces=100,
                                                       density_every=10, eval_every=0), progress=False).report


def test_waits_before_top_level_sections_are_their_own_row():
    """Time a top-level section's start synchronisation apart (once: the nested sections' are inside it), so that
    the profile's "outside any section" is host time and the table names the profile's own waits."""
    calls = []

    def sync():
        calls.append(1)
        time.sleep(0.01)

    t = Timers(sync=sync)
    t0 = time.perf_counter()
    for _ in range(3):
        with t("outer"), section("inner"):
            pass
    p = t.profile(time.perf_counter() - t0)
    assert len(calls) == 3 * 4  # a start (timed apart) and an end per top-level section, a start and end per nested
    # three timed-apart waits; the sections hold the other nine (sleeps only ever run long)
    assert p["sync_s"] >= 0.03 and p["sections_s"] >= 0.09
    assert abs(p["sections_s"] + p["sync_s"] + p["outside_s"] - p["wall_s"]) < 5e-3  # each rounded to 1 ms
    assert "waits before sections (profile)" in format_profile(p)
    assert "waits before" not in format_profile(Timers().profile(1.0))


def test_cli_profile_flag_sets_runtime_profile():
    """Map ``wtopo fit --profile`` to ``runtime.profile`` (off without the flag)."""
    from wtopo.cli import _config, build_parser

    on = build_parser().parse_args(["fit", "bunny", "--out", "x", "--profile"])
    off = build_parser().parse_args(["fit", "bunny", "--out", "x"])
    assert _config(on).runtime.profile is True and _config(off).runtime.profile is False
