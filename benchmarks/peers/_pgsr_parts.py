# SPDX-License-Identifier: Apache-2.0
"""``split.json``: what ``run_pgsr.py --resume`` needs to go on with a stage that ``--stop-at`` / ``--stop-after``
ended (the warm-up with ``--no-mesh-stage``, else the mesh stage), and the figures of the parts so far."""

from __future__ import annotations

import json
import os
import shutil
import sys

from _result import read_json


def stage_of(a) -> tuple[str, int]:
    """The stage a split stops and resumes: its model folder under OUT and its iteration count."""
    return ("warmup", a.warmup_iterations) if a.no_mesh_stage else ("model", a.iterations)


def split_key(a, ex_id: str) -> dict:
    """What a resume must share with the run it goes on with."""
    folder, iterations = stage_of(a)
    return {"exchange": ex_id, "stage": folder, "iterations": iterations, "mesh_train_args": a.mesh_train_args,
            "dpsr_grids_cached": bool(a.cache_dpsr_grids)}


def read_split(a, ex_id: str) -> dict:
    """OUT's ``split.json`` (``write_split``), checked against this run's arguments and for its files."""
    path = os.path.join(a.out, "split.json")
    if not os.path.isfile(path):
        sys.exit(f"--resume: no split.json in {a.out} (the folder of a run that --stop-at or --stop-after ended, "
                 "with its carried files; a finished one keeps it as split_done.json)")
    split = read_json(path)
    split["key"].setdefault("stage", "model")  # written before the warm-up could split: a mesh stage's
    for k, v in split_key(a, ex_id).items():
        if split["key"].get(k) != v:
            sys.exit(f"--resume: {path} stopped a run with {k}={split['key'].get(k)!r}, this one has {v!r}")
    missing = [f for f in split["carry"] if not os.path.isfile(os.path.join(a.out, f))]
    if missing:
        sys.exit(f"--resume: {a.out} lacks {', '.join(missing)} (split.json's carry)")
    return split


def write_split(out: str, a, ex_id: str, it: int, earlier, split, wall: float, times: dict, peak_bytes: int,
                device) -> None:
    """After the stage stopped at its checkpoint of iteration ``it``: OUT's ``split.json``, what ``--resume``
    reads (the figures so far; ``carry``: the files it needs, relative to OUT)."""
    folder = stage_of(a)[0]
    ckpt = [f"{folder}/chkpnt{it}.pth", f"{folder}/chkpnt{it}_state.pth", f"{folder}/app_model/iteration_{it}/app.pth"]
    missing = [f for f in ckpt if not os.path.isfile(os.path.join(out, f))]
    if missing:
        sys.exit(f"run_pgsr: the {'warm-up' if a.no_mesh_stage else 'mesh stage'} ended without its checkpoint of "
                 f"iteration {it}: no {', '.join(missing)}")
    # the mesh stage's restart reads the warm-up's mesh (in the source folder, which is not carried)
    init = [] if a.no_mesh_stage else ["mesh_init.ply"]
    if init and not split:
        shutil.copyfile(os.path.join(out, "source", "mesh_init.ply"), os.path.join(out, "mesh_init.ply"))
    prev = split or {"split_at": [], "restart_s": [], "devices": []}
    doc = {"key": split_key(a, ex_id), "stopped_at": it, "warmup_iterations": a.warmup_iterations,
           "wall_s": wall, "times": times, "peak_gpu_bytes": peak_bytes,
           "split_at": [*prev["split_at"], it], "restart_s": prev["restart_s"], "devices": [*prev["devices"], device],
           "earlier": None if not earlier else {"from": earlier["from"], "device": earlier["device"]},
           "carry": ["split.json", *init, *ckpt]}
    with open(os.path.join(out, "split.json.part"), "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(os.path.join(out, "split.json.part"), os.path.join(out, "split.json"))
    print(f"run_pgsr: the {'warm-up' if a.no_mesh_stage else 'mesh stage'} stopped after iteration {it}; carry "
          f"{', '.join(doc['carry'])} (under {out}) and go on with --resume", file=sys.stderr)


def drop_later_app_weights(folder: str, stopped_at: int) -> None:
    """A resume attempted before left later appearance weights, which the restart would load (the highest)."""
    apps = os.path.join(folder, "app_model")
    for d in os.listdir(apps):
        if d.startswith("iteration_") and int(d.split("_")[1]) > stopped_at:
            shutil.rmtree(os.path.join(apps, d))
