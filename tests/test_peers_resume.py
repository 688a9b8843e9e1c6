# SPDX-License-Identifier: Apache-2.0
"""``benchmarks/peers/run_pgsr.py --stop-at`` / ``--stop-after`` / ``--resume``: the TopoSurfel authors' code at its
published 30,000 + 10,000 iterations across device leases, on the CPU with its children stood in for
(``peers_fakes.py``): what each part runs, what it leaves for the next, and the figures of the whole."""

from __future__ import annotations

import json
import os

import pytest
from peers_fakes import fake_pgsr, small_exchange


@pytest.fixture(scope="module")
def exch(tmp_path_factory):
    return small_exchange(tmp_path_factory)


def _checkouts(tmp_path, init="pgsr_init"):
    for name in ("pgsr_dpsr", init):
        (tmp_path / name).mkdir()
        (tmp_path / name / "train.py").write_text("")
    return ["--checkout", str(tmp_path / "pgsr_dpsr"), "--init-checkout", str(tmp_path / init)]


def test_the_authors_mesh_stage_stops_at_a_checkpoint_and_resumes(exch, tmp_path, monkeypatch):
    """``run_pgsr.py --stop-at N`` then ``--resume`` (in a later lease, OUT carried): the mesh stage's ``train.py``
    runs under ``_pgsr_split.py``, writes its checkpoint and stops without a mesh; the resume restarts from that
    checkpoint and its state, and the result counts every part's time and the warm-up's, less the restart's setup.
    Splits that would change the camera order, and a resume of another run, are refused before anything runs."""
    _checkouts(tmp_path)
    (tmp_path / "absent").mkdir()  # the mesh stage from a carried warm-up needs no warm-up checkout
    ck = ["--checkout", str(tmp_path / "pgsr_dpsr"), "--init-checkout", str(tmp_path / "absent")]
    calls = []
    run_pgsr = fake_pgsr(monkeypatch, calls)
    run_pgsr.main([exch.root, str(tmp_path / "warm"), "--checkout", str(tmp_path / "pgsr_dpsr"), "--no-mesh-stage",
                   "--warmup-iterations", "300"])
    out, views = tmp_path / "split", len(exch.train)
    base = [exch.root, str(out), *ck, "--iterations", str(10 * views), "--cache-dpsr-grids"]
    for bad in (views + 1, 10 * views, 0):
        with pytest.raises(SystemExit, match="multiple of the"):
            run_pgsr.main([*base, "--from-warmup", str(tmp_path / "warm"), "--stop-at", str(bad)])
    with pytest.raises(SystemExit, match="no split.json"):
        run_pgsr.main([*base, "--resume"])

    calls.clear()
    run_pgsr.main([*base, "--from-warmup", str(tmp_path / "warm"), "--stop-at", str(4 * views)])
    assert len(calls) == 1  # training only: no mesh, no held-out views, no result
    train = calls[0][1]
    assert [os.path.basename(c) for c in train[3:6]] == ["_pgsr_split.py", "_dpsr_cache.py", "train.py"]
    assert train[train.index("--checkpoint_iterations") + 1] == str(4 * views)
    split = json.loads((out / "split.json").read_text())
    assert split["stopped_at"] == 4 * views and not (out / "run.json").exists()
    assert all((out / f).is_file() for f in split["carry"]) and "mesh_init.ply" in split["carry"]
    assert split["wall_s"] >= split["times"]["warmup_train_s"] and split["peak_gpu_bytes"] == 1000
    # as if the first part had run on a larger GPU for an hour: the result must carry both on
    split.update(peak_gpu_bytes=7777, wall_s=3600.0, times={**split["times"], "train_s": 3000.0})
    (out / "split.json").write_text(json.dumps(split))

    with pytest.raises(SystemExit, match="stopped a run with iterations="):  # another run's split
        run_pgsr.main([exch.root, str(out), *ck, "--iterations", str(20 * views), "--cache-dpsr-grids", "--resume"])
    with pytest.raises(SystemExit, match="multiple of the"):  # not beyond where it stopped
        run_pgsr.main([*base, "--resume", "--stop-at", str(2 * views)])

    calls.clear()
    (out / "model" / "app_model" / "iteration_9999").mkdir()  # as an earlier attempt to resume would leave
    run_pgsr.main([*base, "--resume"])
    assert os.listdir(out / "model" / "app_model") == [f"iteration_{4 * views}"]  # their restart loads the highest
    train = calls[0][1]
    ckpt = train[train.index("--start_checkpoint") + 1]
    assert ckpt == str(out / "model" / f"chkpnt{4 * views}.pth") and "--checkpoint_iterations" not in train
    assert calls[0][2]["PGSR_SPLIT_STATE"] == str(out / "model" / f"chkpnt{4 * views}_state.pth")
    assert [c[1][3] for c in calls[1:2]] == ["render.py"]  # now its TSDF mesh, then the held-out views
    whole = json.loads((out / "run.json").read_text())
    assert whole["system"] == (f"PGSR+DPSR (authors', 300 + {10 * views} it.) [DPSR grids on the GPU] "
                               f"[split at {4 * views}]")
    assert whole["split_at"] == [4 * views] and whole["split_restart_s"] == [pytest.approx(0.25, abs=0.2)]
    assert whole["warmup_train_s"] == split["times"]["warmup_train_s"] and "an earlier run" in whole["warmup_from"]
    assert whole["peak_gpu_bytes"] == 7777
    # this part took well under a second (its training less the 0.25 s restart, its mesh): an hour and less than 1 s
    assert 3600.0 - 0.5 < whole["wall_s"] < 3600.0 + 1.0
    assert 3000.0 - 0.5 < whole["train_s"] < 3000.0 - 0.1  # the restart's 0.25 s of setup not counted

    # --stop-after: where it stopped comes back from the launcher; a long enough time trains to the end
    calls.clear()
    run_pgsr.main([*base[:1], str(tmp_path / "timed"), *base[2:], "--from-warmup", str(tmp_path / "warm"),
                   "--stop-after", "60"])
    train = calls[0][1]
    assert "--checkpoint_iterations" not in train and len(calls) == 1
    timed = json.loads((tmp_path / "timed" / "split.json").read_text())
    assert timed["stopped_at"] == 2 * views and timed["split_at"] == [2 * views]
    calls.clear()
    run_pgsr.main([*base[:1], str(tmp_path / "timed"), *base[2:], "--resume", "--stop-after", "500"])
    assert [c[1][3] for c in calls[1:2]] == ["render.py"]  # it got to the end first: its mesh and result
    assert json.loads((tmp_path / "timed" / "run.json").read_text())["split_at"] == [2 * views]
    with pytest.raises(SystemExit, match="split_done.json"):  # finished: nothing to go on with
        run_pgsr.main([*base[:1], str(tmp_path / "timed"), *base[2:], "--resume"])
    with pytest.raises(SystemExit):
        run_pgsr.main([*base, "--resume", "--stop-at", str(6 * views), "--stop-after", "5"])


def test_the_authors_warmup_stops_at_a_checkpoint_and_resumes(exch, tmp_path, monkeypatch):
    """``--no-mesh-stage`` with ``--stop-at`` then ``--resume``: their warm-up (plain PGSR: the row without the mesh
    stage, and the mesh stage's start) in two leases. The first part trains under ``_pgsr_split.py`` to its
    checkpoint in the warm-up's folder; the resume trains on from it, makes its TSDF mesh and the result, which
    counts both parts' time, and then starts a mesh stage as a whole warm-up's does."""
    ck = _checkouts(tmp_path)
    calls = []
    run_pgsr = fake_pgsr(monkeypatch, calls)
    out, views = tmp_path / "warm", len(exch.train)
    base = [exch.root, str(out), *ck, "--no-mesh-stage", "--warmup-iterations", str(10 * views)]
    with pytest.raises(SystemExit, match="multiple of the"):  # the warm-up's iterations bound it, not the mesh's
        run_pgsr.main([*base, "--stop-at", str(10 * views)])
    with pytest.raises(SystemExit):  # a split warm-up is a run of its own, not one the mesh stage goes on from
        run_pgsr.main([exch.root, str(tmp_path / "both"), *ck, "--nomesh-out", str(tmp_path / "no"),
                       "--stop-at", str(4 * views)])
    assert not calls

    run_pgsr.main([*base, "--stop-at", str(4 * views)])
    assert [c[0] for c in calls] == ["pgsr_init"]  # training only: no mesh, no held-out views, no result
    train = calls[0][1]
    assert [os.path.basename(c) for c in train[3:5]] == ["_pgsr_split.py", "train.py"]
    split = json.loads((out / "split.json").read_text())
    assert split["key"]["stage"] == "warmup" and split["stopped_at"] == 4 * views
    assert split["carry"] == ["split.json", f"warmup/chkpnt{4 * views}.pth", f"warmup/chkpnt{4 * views}_state.pth",
                              f"warmup/app_model/iteration_{4 * views}/app.pth"]
    assert all((out / f).is_file() for f in split["carry"]) and not (out / "run.json").exists()
    with pytest.raises(SystemExit, match="stopped a run with stage="):  # a mesh stage cannot go on from it
        run_pgsr.main([exch.root, str(out), *ck, "--warmup-iterations", str(10 * views), "--resume"])
    split.update(wall_s=3600.0, times={"warmup_train_s": 3000.0})  # as if the first part had taken an hour
    (out / "split.json").write_text(json.dumps(split))

    calls.clear()
    (out / "warmup" / "app_model" / "iteration_9999").mkdir()  # as an earlier attempt to resume would leave
    run_pgsr.main([*base, "--resume"])
    assert os.listdir(out / "warmup" / "app_model") == [f"iteration_{4 * views}"]
    assert [c[0] for c in calls] == ["pgsr_init"] * 3  # training, its TSDF mesh, the held-out views
    train = calls[0][1]
    assert train[train.index("--start_checkpoint") + 1] == str(out / "warmup" / f"chkpnt{4 * views}.pth")
    assert calls[0][2]["PGSR_SPLIT_STATE"] == str(out / "warmup" / f"chkpnt{4 * views}_state.pth")
    whole = json.loads((out / "run.json").read_text())
    assert whole["system"] == f"PGSR (authors', {10 * views:,} it.) [split at {4 * views}]"
    assert whole["split_at"] == [4 * views] and whole["mesh_stage_iterations"] is None
    assert 3000.0 - 0.5 < whole["warmup_train_s"] < 3000.0 - 0.1  # the restart's 0.25 s of setup not counted
    assert 3600.0 - 0.5 < whole["wall_s"] < 3600.0 + 1.0 and whole["warmup_mesh_s"] >= 0
    assert (out / "split_done.json").is_file() and not (out / "split.json").exists()

    calls.clear()  # the next lease: the mesh stage from the split warm-up's result, as from a whole one's
    run_pgsr.main([exch.root, str(tmp_path / "mesh"), *ck, "--iterations", str(10 * views), "--from-warmup", str(out)])
    mesh = json.loads((tmp_path / "mesh" / "run.json").read_text())
    assert "[split at" in mesh["warmup_from"] and mesh["warmup_train_s"] == whole["warmup_train_s"]
    assert mesh["wall_s"] > whole["wall_s"]  # the warm-up's parts and this stage
