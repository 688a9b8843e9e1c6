# SPDX-License-Identifier: Apache-2.0
"""The hard-scene suite's fits N at once (``hard.py --jobs N``): one process per (scene, variant, seed),
each pinned to its own ``--cores-per-job`` cores.

A fit on the CPU uses a few cores well (Warp's CPU launches run on one thread each, split by
``wtopo._bridge`` over the cores the process may use) and a many-core machine no better, so a suite of
dozens of fits is fastest as one fit per small set of cores. Every case runs ``hard.py`` itself for one
scene, variant and seed, with the same ``--set``, ``--device``, ``--gpu``, ``--resolution`` and
``--mesh-cache``, writing its fit folder where the sequential runner would (``<run-dir>/<label>/seed<S>/
<scene>_<variant>``, so ``--rescore`` finds it) and its row to a file of its own, which this parent adds to
``rows.json`` and the ``--out`` section as each case ends. A case whose process fails is recorded as an
``error`` row naming its log (``<run-dir>/<label>/logs/``); one stopped by a signal is not recorded, as in
the sequential runner. Ctrl-C or SIGTERM to the parent stops every case and keeps what has ended.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

INTERRUPTED = 130  # a case's exit status when its fit was stopped by a signal (hard.py's FitInterrupted)


@dataclass(frozen=True)
class Case:
    """One fit of the suite: a scene, a variant and a seed (``None``: the runner's default seed)."""

    scene: str
    variant: str
    seed: int | None

    @property
    def name(self) -> str:
        return f"{self.scene}_{self.variant}" + ("" if self.seed is None else f"_seed{self.seed}")


def core_slots(jobs: int, cores_per_job: int, available: Sequence[int] | None = None) -> list[list[int]]:
    """``jobs`` disjoint lists of ``cores_per_job`` core ids from the cores this process may use.

    Raises:
        ValueError: ``jobs`` or ``cores_per_job`` under 1, or more cores asked for than there are.
    """
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    if cores_per_job < 1:
        raise ValueError(f"--cores-per-job must be at least 1, got {cores_per_job}")
    if available is None and not hasattr(os, "sched_getaffinity"):
        raise ValueError("--jobs pins each case to its cores with os.sched_setaffinity, which only Linux has")
    cores = sorted(available if available is not None else os.sched_getaffinity(0))
    if jobs * cores_per_job > len(cores):
        raise ValueError(f"--jobs {jobs} x --cores-per-job {cores_per_job} needs {jobs * cores_per_job} cores; "
                         f"this process may use {len(cores)} ({cores})")
    return [cores[i * cores_per_job:(i + 1) * cores_per_job] for i in range(jobs)]


def case_command(case: Case, rows_file: str, *, script: str, run_dir: str, label: str, device: str,
                 sets: Sequence[str] = (), gpu: bool = False, resolution: int | None = None,
                 mesh_cache: str | None = None) -> list[str]:
    """The ``hard.py`` command line that fits ``case`` alone and writes its row to ``rows_file``."""
    cmd = [sys.executable, script, "--scenes", case.scene, "--variants", case.variant, "--device", device,
           "--run-dir", run_dir, "--label", label, "--rows-file", rows_file]
    if case.seed is not None:
        cmd += ["--seeds", str(case.seed)]
    for s in sets:
        cmd += ["--set", s]
    if gpu:
        cmd.append("--gpu")
    if resolution:
        cmd += ["--resolution", str(resolution)]
    if mesh_cache:
        cmd += ["--mesh-cache", mesh_cache]
    return cmd


def run_cases(cases: Sequence[Case], command: Callable[[Case, str], list[str]], slots: Sequence[Sequence[int]],
              work_dir: str, on_row: Callable[[dict], None], poll_s: float = 0.5) -> int:
    """Run every case's ``command(case, rows_file)`` with at most ``len(slots)`` at once, each process
    pinned to one slot's cores (and its OpenMP / MKL threads set to their number), calling ``on_row``
    with each case's row as it ends, in the order they end.

    A process that exits 0 without writing its row, or exits non-zero, gives an ``error`` row naming
    its log; one that exits 130 (its fit was stopped by a signal) gives none.

    Returns:
        0, or 130 if the parent was interrupted (its running cases are stopped and not recorded).
    """
    logs = os.path.join(work_dir, "logs")
    os.makedirs(logs, exist_ok=True)
    queue = list(cases)
    free = [list(s) for s in slots]
    running: dict[subprocess.Popen, tuple[Case, list[int], str, str, float]] = {}
    stop = {"signal": None}

    def _stop(signum, _frame):
        stop["signal"] = signum

    old = signal.signal(signal.SIGTERM, _stop)
    try:
        while queue or running:
            while queue and free and stop["signal"] is None:
                case, cores = queue.pop(0), free.pop(0)
                rows_file = os.path.join(work_dir, f".row_{case.name}.json")
                if os.path.exists(rows_file):
                    os.remove(rows_file)
                log = os.path.join(logs, f"{case.name}.log")
                env = {**os.environ, "OMP_NUM_THREADS": str(len(cores)), "MKL_NUM_THREADS": str(len(cores))}
                with open(log, "w") as fh:
                    p = subprocess.Popen(command(case, rows_file), stdout=fh, stderr=subprocess.STDOUT, env=env,
                                         preexec_fn=lambda c=tuple(cores): os.sched_setaffinity(0, c))
                running[p] = (case, cores, rows_file, log, time.perf_counter())
                print(f"[{case.name}] started on cores {cores[0]}-{cores[-1]}", flush=True)
            if stop["signal"] is not None:
                raise KeyboardInterrupt
            time.sleep(poll_s)
            for p in [p for p in running if p.poll() is not None]:
                case, cores, rows_file, log, t0 = running.pop(p)
                free.append(cores)
                row = _case_row(case, p.returncode, rows_file, log, time.perf_counter() - t0)
                if row is not None:
                    on_row(row)
    except KeyboardInterrupt:
        for p in running:
            p.terminate()
        for p in running:
            p.wait()
        print(f"interrupted: {len(running)} running case(s) stopped, not recorded", flush=True)
        return INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, old)
    return 0


def _case_row(case: Case, returncode: int, rows_file: str, log: str, elapsed: float) -> dict | None:
    if returncode == INTERRUPTED:
        print(f"[{case.name}] stopped by a signal: not recorded (log {log})", flush=True)
        return None
    rows = []
    if returncode == 0 and os.path.exists(rows_file):
        with open(rows_file) as f:
            rows = json.load(f)
    if len(rows) != 1:
        err = f"case process exited {returncode} with {len(rows)} rows; see {log}"
        print(f"[{case.name}] {err}", flush=True)
        row = {"scene": case.scene, "variant": case.variant, "error": err, "time": elapsed}
        return row if case.seed is None else {**row, "seed": case.seed}
    os.remove(rows_file)
    print(f"[{case.name}] done in {elapsed:.0f} s: Chamfer {rows[0].get('chamfer', float('nan')):.3f} %", flush=True)
    return rows[0]


def sort_rows(rows: list[dict], scenes: Sequence[str], variants: Sequence[str]) -> list[dict]:
    """``rows`` in the sequential runner's order: by scene, then seed, then variant, as the command
    listed them; rows of other scenes or variants (an earlier run's, kept by ``--resume``) first."""
    def key(r):
        if r["scene"] not in scenes or r["variant"] not in variants:
            return (-1, 0, 0)
        return (scenes.index(r["scene"]), r.get("seed") if r.get("seed") is not None else -1,
                variants.index(r["variant"]))
    return sorted(rows, key=key)
