# SPDX-License-Identifier: Apache-2.0
"""The benchmark scripts run on the CPU at their smallest settings. They reach into the package's internals (the
plan's budgets, the fit's stages, the kernels' wrappers), so a refactor that breaks one shows here rather than at
the next measurement."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"

# script, arguments (outputs, when a script writes any, go to the test's folder: {tmp}), a line its output must have
SMOKE = [
    ("bench_rasterize.py", ["--sizes", "1000", "--res", "64", "--repeats", "1", "--fit-path"], "N=1000: intersections"),
    ("bench_losses.py", ["--quick", "--repeats", "1"], "photo (fused Warp)"),
    # four views: too few for the multi-view term's neighbours, which the table then leaves out
    ("bench_losses.py", ["--warmup", "10", "--repeats", "1", "--views", "4", "--resolution", "64"], "photo"),
    ("bench_proxy_chain.py", ["--device", "cpu", "--resolution", "32", "--view", "32", "--points", "2000",
                              "--surfels", "1000", "--repeats", "1", "--json", "{tmp}/chain.json"], '"forward_ms"'),
    ("bench_mesh_policy.py", ["--subdivisions", "4", "--device", "cpu"], "supported faces on cpu"),
    ("tsdf.py", ["--device", "cpu", "--views", "4", "--sizes", "80x60", "--grids", "32", "--repeats", "1"],
     "80x60    32"),
    ("bench_optimizer.py", ["--device", "cpu", "--surfels", "1000", "--steps", "3"], "     1000 "),
    ("bench_bridge.py", ["--device", "cpu", "--resolution", "32", "--calls", "5"], "photometric  fwd+bwd"),
    # the stability sweep loads tests/test_stability.py and what it imports by file path
    ("stability.py", ["--cases", "tsdf_empty", "empty_masks", "--md", "{tmp}/stability.md"], "tsdf_empty"),
]


@pytest.mark.parametrize("script,args,expect", SMOKE, ids=[f"{s}:{i}" for i, (s, _, _) in enumerate(SMOKE)])
def test_benchmark_script_runs(script, args, expect, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, str(BENCH / script), *(a.replace("{tmp}", str(tmp_path)) for a in args)]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"{script} failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    assert expect.lower() in (r.stdout + r.stderr).lower(), r.stdout[-2000:]


def test_bench_fit_runs_and_writes_its_table(tmp_path):
    sys.path.insert(0, str(BENCH))
    try:
        import bench_fit

        out = tmp_path / "fit.md"
        assert bench_fit.main(["--scene", "sphere", "--iterations", "16", "--variants", "no_mesh_loop",
                               "--device", "cpu", "--out", str(out)]) == 0
    finally:
        sys.path.remove(str(BENCH))
        sys.modules.pop("bench_fit", None)
    text = out.read_text()
    assert "`sphere` scene" in text
    row = next(line for line in text.splitlines() if line.startswith("| no_mesh_loop | 0 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert float(cells[4]) > 0.0 and 0.0 <= float(cells[6]) <= 1.0  # Chamfer %, F-score


def test_error_vs_runtime_names_every_timer_of_a_fit(tmp_path):
    """Every timer a fit reports is in one of error_vs_runtime.py's stage columns or its bookkeeping list, so a
    renamed or new timer cannot fall silently into ``other`` (the columns had lost the initialisation's)."""
    from wtopo import scenes
    from wtopo.fitting import FitConfig, fit

    sys.path.insert(0, str(BENCH))
    try:
        import error_vs_runtime as evr
    finally:
        sys.path.remove(str(BENCH))
        sys.modules.pop("error_vs_runtime", None)
    known = {t for timers in evr.STAGES.values() for t in timers} | set(evr.OTHER)
    assert not set(evr.OTHER) & {t for timers in evr.STAGES.values() for t in timers}
    cfg = FitConfig()
    cfg.warmup.iterations, cfg.coevolution.iterations, cfg.polish.iterations = 12, 8, 4
    cfg.runtime.eval_every, cfg.runtime.usd_every, cfg.runtime.device = 0, 0, "cpu"
    res = fit(scenes.load("sphere"), cfg, out_dir=str(tmp_path), progress=False)
    timers = set(res.report["stage_times_s"])
    assert {"init_seed", "rasterize_forward", "marching_cubes", "tsdf_integrate", "outline"} <= timers  # every stage
    assert timers <= known, f"timers error_vs_runtime.py does not name: {sorted(timers - known)}"
