"""The hard-scene suite's parallel runner (``lab/hard_parallel.py``, ``hard.py --jobs``)."""

import json
import os
import sys
import textwrap

import lab.hard as hard
import pytest
from lab.hard_parallel import Case, case_command, core_slots, run_cases, sort_rows

needs_affinity = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="Linux core affinity")

# a stand-in for hard.py's single-case run: records the cores and threads it was given, then behaves as
# its scene name says (writes its row, exits 130 as a signal-stopped fit, fails, or writes no row)
_FAKE = textwrap.dedent("""
    import json, os, sys, time
    scene, rows_file = sys.argv[1], sys.argv[2]
    time.sleep(0.3)
    if scene == "stopped":
        sys.exit(130)
    if scene == "crash":
        raise RuntimeError("boom")
    if scene != "silent":
        row = {"scene": scene, "variant": "v", "seed": 0, "chamfer": 0.1,
               "cores": sorted(os.sched_getaffinity(0)), "omp": os.environ.get("OMP_NUM_THREADS")}
        with open(rows_file, "w") as f:
            json.dump([row], f)
""")


def _fake(tmp_path):
    script = tmp_path / "fake_case.py"
    script.write_text(_FAKE)
    return lambda case, rows_file: [sys.executable, str(script), case.scene, rows_file]


@needs_affinity
def test_core_slots_are_disjoint_and_bad_counts_name_the_argument():
    assert core_slots(3, 2, available=[7, 0, 1, 2, 3, 4, 5]) == [[0, 1], [2, 3], [4, 5]]
    with pytest.raises(ValueError, match="--jobs must be at least 1, got 0"):
        core_slots(0, 2, available=[0, 1])
    with pytest.raises(ValueError, match="--cores-per-job must be at least 1, got 0"):
        core_slots(1, 0, available=[0, 1])
    with pytest.raises(ValueError, match=r"--jobs 2 x --cores-per-job 2 needs 4 cores; this process may use 3"):
        core_slots(2, 2, available=[0, 1, 2])


@needs_affinity
def test_each_case_runs_pinned_to_its_slot_and_failures_are_recorded(tmp_path):
    """Every case runs once, on exactly one slot's cores with OMP threads to match; a crash and a
    process that writes no row are ``error`` rows naming their log; a signal-stopped case (130) is not
    recorded, and the cases after it still run."""
    cores = sorted(os.sched_getaffinity(0))
    slots = [[c] for c in cores[:2]]
    cases = [Case(s, "v", 0) for s in ("a", "stopped", "b", "crash", "silent", "c")]
    rows = []
    assert run_cases(cases, _fake(tmp_path), slots, str(tmp_path), rows.append, poll_s=0.05) == 0
    by_scene = {r["scene"]: r for r in rows}
    assert sorted(by_scene) == ["a", "b", "c", "crash", "silent"], "every case but the stopped one gave a row"
    for s in "abc":
        assert by_scene[s]["cores"] in slots and by_scene[s]["omp"] == "1"
    for s in ("crash", "silent"):
        err = by_scene[s]["error"]
        assert "see" in err and err.endswith(f"{s}_v_seed0.log") and by_scene[s]["seed"] == 0
    assert "RuntimeError: boom" in (tmp_path / "logs" / "crash_v_seed0.log").read_text()
    assert not list(tmp_path.glob(".row_*")), "a recorded case's row file is removed"


def test_rows_keep_the_sequential_runners_order():
    rows = [{"scene": "b", "variant": "x", "seed": 1}, {"scene": "a", "variant": "y", "seed": 0},
            {"scene": "old", "variant": "x", "seed": 0}, {"scene": "a", "variant": "x", "seed": 0},
            {"scene": "b", "variant": "x", "seed": 0}]
    got = [(r["scene"], r["variant"], r["seed"]) for r in sort_rows(rows, ["a", "b"], ["x", "y"])]
    assert got == [("old", "x", 0), ("a", "x", 0), ("a", "y", 0), ("b", "x", 0), ("b", "x", 1)]


def test_a_case_command_fits_one_case_where_the_sequential_runner_would():
    cmd = case_command(Case("torus", "no_loop", 1), "/r/.row.json", script="hard.py", run_dir="/runs", label="L",
                       device="cpu", sets=["a.b=1"], gpu=True, resolution=64, mesh_cache="/mc")
    assert cmd[1:] == ["hard.py", "--scenes", "torus", "--variants", "no_loop", "--device", "cpu", "--run-dir",
                       "/runs", "--label", "L", "--rows-file", "/r/.row.json", "--seeds", "1", "--set", "a.b=1",
                       "--gpu", "--resolution", "64", "--mesh-cache", "/mc"]
    assert "--seeds" not in case_command(Case("torus", "default", None), "f", script="h", run_dir="r", label="L",
                                         device="cpu")


@pytest.mark.slow
@needs_affinity
def test_jobs_fit_the_suite_two_at_once(tmp_path):
    """``hard.py --jobs 2``: two tiny real fits at once, their rows in ``rows.json`` and the ``--out``
    section in the sequential order, each fit folder where ``--rescore`` looks for it."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs two cores")
    out = tmp_path / "hard.md"
    argv = ["--scenes", "torus", "--variants", "default", "no_loop", "--seeds", "0", "--jobs", "2",
            "--cores-per-job", "1", "--resolution", "24", "--set", "warmup.iterations=20",
            "--set", "coevolution.iterations=10", "--set", "runtime.eval_metrics=false",
            "--run-dir", str(tmp_path), "--label", "par", "--out", str(out)]
    assert hard.main(argv) == 0
    rows = json.loads((tmp_path / "par" / "rows.json").read_text())
    assert [(r["scene"], r["variant"], r["seed"]) for r in rows] == [("torus", "default", 0), ("torus", "no_loop", 0)]
    assert all("error" not in r and r["chamfer"] > 0 for r in rows), rows
    for v in ("default", "no_loop"):
        assert (tmp_path / "par" / "seed0" / f"torus_{v}" / "mesh.ply").exists()
    text = out.read_text()
    assert "## par" in text and "| torus (seed 0) | default |" in text and "| torus (seed 0) | no_loop |" in text
    assert hard.main([*argv, "--resume"]) == 0, "a resumed run with every case done runs nothing"
    assert len(json.loads((tmp_path / "par" / "rows.json").read_text())) == 2
