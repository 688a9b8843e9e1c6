# SPDX-License-Identifier: Apache-2.0
"""The TopoSurfel authors' code (``Fan-Treasure/pgsr_dpsr``) on an exchange folder (the peers benchmark).

PGSR with a DPSR proxy mesh, with and without its mesh stage.

Its ``train.py`` starts from a per-scene ``mesh_init.ply`` in the source folder (``train.py:110-113``, no
fallback) that nothing in the repository makes. So, in two stages, each with the repository's own DTU
recipe (``scripts/run_dtu.py``: ``train.py -r2 --ncc_scale 0.5``, then ``render.py --num_cluster 1
--voxel_size 0.002 --max_depth 5.0`` with ``OMP_NUM_THREADS=4``):

1. warm-up: the same repository's earlier plain-PGSR commit (``de24f1a``, ``--init-checkout``) trains
   30,000 iterations (its default) from the exchange folder's initial points; its TSDF mesh
   (``mesh/tsdf_fusion_post.ply``) becomes ``mesh_init.ply``;
2. mesh stage: the newest commit (``--checkout``) trains 10,000 iterations (its default) from that mesh,
   with the DPSR proxy mesh from iteration 5,000 (mesh-guided normal flips, mesh-guided densification,
   mesh depth / normal losses), and its ``render.py`` makes the TSDF mesh that is scored.

``--no-mesh-stage`` stops after stage 1 and scores the warm-up's own mesh: plain PGSR, the authors'
code without its mesh stage. ``-r 1`` instead of ``-r2``: the exchange folder is already at the
training resolution (as for 2DGS); ``--ncc_scale 0.5`` is kept (the NCC patches then span the same
training pixels as in the recipe). No ``--eval``: the COLMAP model holds the training views only, and
the held-out views are rendered afterwards with the checkout's renderer (``_peer_views.py``). The source
folder PGSR reads (``sparse/*.txt``: the recipe's ``cp sparse/0/* sparse/``; ``images`` linked;
``mesh_init.ply``) is made under OUT, since PGSR writes into it. Needs the CUDA extensions
``diff_plane_rasterization``, ``simple_knn``, and for the mesh stage ``nvdiffrast`` and ``diso``
importable, and ``shims/`` (pytorch3d, pymeshlab, kaolin, igl stand-ins) on the path.

    python benchmarks/peers/run_pgsr.py EXCH OUT --checkout PATH [--init-checkout PATH] [--no-mesh-stage]
        [--iterations 10000] [--warmup-iterations 30000] [--nomesh-out DIR] [--mesh-only ITERATION]
        [--from-warmup DIR] [--mesh-train-args "ARGS"] [--cache-dpsr-grids] [--stop-at ITERATION | --stop-after S]
        [--resume]

``--nomesh-out DIR`` also writes the warm-up's own result (plain PGSR, timed alone) from the same run.
``--from-warmup DIR`` runs stage 2 alone from an earlier ``--no-mesh-stage`` run's result folder (the mesh
stage reads nothing of the warm-up but its TSDF mesh): the recipe in two leases, with the warm-up's time and
peak memory counted in the result's. ``--mesh-train-args`` passes more arguments to the mesh stage's
``train.py`` (a short check of its DPSR half before a whole run, e.g. ``--mesh-train-args=--mesh_from_iter=200``,
one word for ``device.sh``'s ``PGSR_ARGS``): the result's system name then says so. ``--cache-dpsr-grids``
runs the mesh stage's ``train.py`` under ``_dpsr_cache.py``: its DPSR builds its 512^3 frequency grid on the
CPU and copies it and its filter to the GPU every iteration (about 1 GiB), which bounds its loop by the host;
the cache keeps them on the GPU, the same values, and the system name says so. ``run.json`` names the GPU each
stage ran on.

``--stop-at N`` ends the mesh stage (with ``--no-mesh-stage``, the warm-up) after its checkpoint of iteration N, a
multiple of the number of training views (``_pgsr_split.py`` says why), ``--stop-after SECONDS`` at the first such
iteration that its ``train.py`` ends SECONDS after its start (for a lease of known length), and ``--resume`` goes
on from it in OUT, on this machine or another: each published stage in two leases or more. A split warm-up's
result starts a mesh stage (``--from-warmup``) as a whole one's does. OUT's ``split.json`` names the files a resume
needs (``carry``) and holds the parts' figures so far; the result counts every part's time, less the setup each
restart repeats (recorded as ``split_restart_s``), the largest peak, and its system name says where it was split.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _pgsr_parts import drop_later_app_weights, read_split, stage_of, write_split  # noqa: E402
from _result import read_json, write_result  # noqa: E402
from exchange import load  # noqa: E402

# the repository's DTU recipe (scripts/run_dtu.py), less -r2 (the exchange folder is at training resolution)
TRAIN_ARGS = ["--quiet", "-r", "1", "--ncc_scale", "0.5"]
MESH_ARGS = ["--quiet", "--num_cluster", "1", "--voxel_size", "0.002", "--max_depth", "5.0"]


def _env() -> dict:
    """The children's environment: the shims on the path, the recipe's OMP_NUM_THREADS=4 for render.py."""
    env = dict(os.environ)
    shims = os.path.join(HERE, "shims")
    path = env.get("PYTHONPATH", "")
    if shims not in path.split(os.pathsep):
        env["PYTHONPATH"] = shims + (os.pathsep + path if path else "")
    return env


def _run(cmd: list[str], cwd: str, log, **env) -> None:
    log.write("$ " + " ".join(cmd) + "\n")
    log.flush()
    subprocess.run(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT, check=True, env={**_env(), **env})


def source_folder(exchange: str, dst: str) -> str:
    """PGSR's source folder for the exchange folder's COLMAP model: ``sparse/{cameras,images,points3D}.txt``
    (copies: PGSR writes ``sparse/points3D.ply`` and reads ``mesh_init.ply`` here) and ``images`` (a link)."""
    col = os.path.abspath(os.path.join(exchange, "colmap"))
    os.makedirs(os.path.join(dst, "sparse"), exist_ok=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        shutil.copyfile(os.path.join(col, "sparse", "0", name), os.path.join(dst, "sparse", name))
    link = os.path.join(dst, "images")
    if not os.path.lexists(link):
        os.symlink(os.path.join(col, "images"), link)
    return os.path.abspath(dst)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exchange")
    ap.add_argument("out")
    ap.add_argument("--checkout", required=True, help="path of a pgsr_dpsr checkout (its newest commit)")
    ap.add_argument("--init-checkout", default=None,
                    help="path of the same repository at its plain-PGSR commit de24f1a (the warm-up); "
                         "default: pgsr_init beside --checkout")
    ap.add_argument("--no-mesh-stage", action="store_true", help="the warm-up (plain PGSR) only")
    ap.add_argument("--iterations", type=int, default=10_000, help="mesh stage (pgsr_dpsr's default)")
    ap.add_argument("--warmup-iterations", type=int, default=30_000, help="warm-up (PGSR's default)")
    ap.add_argument("--nomesh-out", default=None, metavar="DIR",
                    help="also write the warm-up's own result (plain PGSR, its time alone) to DIR")
    ap.add_argument("--mesh-only", type=int, default=None, metavar="ITERATION",
                    help="skip training: mesh and render this iteration's checkpoint of an earlier run "
                         "(the final stage's: the warm-up's with --no-mesh-stage)")
    ap.add_argument("--from-warmup", default=None, metavar="DIR",
                    help="skip the warm-up: start the mesh stage from an earlier --no-mesh-stage run's result "
                         "folder DIR (its warmup/mesh/tsdf_fusion_post.ply and run.json, e.g. carried from "
                         "another machine); its time and peak memory count in the result's")
    ap.add_argument("--mesh-train-args", default="", metavar="ARGS",
                    help="more arguments of the mesh stage's train.py, one string (e.g. \"--mesh_from_iter 200\" "
                         "for a short check of its DPSR half): not the published recipe, and the system name says so")
    ap.add_argument("--stop-at", type=int, default=None, metavar="ITERATION",
                    help="end the mesh stage (the warm-up with --no-mesh-stage) after its checkpoint of ITERATION (a "
                         "multiple of the number of training views, below the stage's iterations): OUT then holds "
                         "what --resume needs, and no result")
    ap.add_argument("--stop-after", type=float, default=None, metavar="SECONDS",
                    help="as --stop-at, at the first multiple of the number of training views that the stage's "
                         "train.py ends SECONDS or more after its start (it goes on to the end if it gets there first)")
    ap.add_argument("--resume", action="store_true",
                    help="go on with the stage that --stop-at or --stop-after ended in OUT (carried from another "
                         "machine, its split.json's files), to its end or to the next stop")
    ap.add_argument("--cache-dpsr-grids", action="store_true",
                    help="the mesh stage's DPSR keeps its frequency grid and filter on the GPU instead of building "
                         "and copying them every iteration (_dpsr_cache.py): the same values, less time; the "
                         "system name says so")
    a = ap.parse_args(argv)
    extra = shlex.split(a.mesh_train_args)
    if (extra or a.cache_dpsr_grids) and (a.no_mesh_stage or a.mesh_only is not None):
        ap.error("--mesh-train-args, --cache-dpsr-grids: --no-mesh-stage and --mesh-only train no mesh stage")
    if a.from_warmup and (a.no_mesh_stage or a.mesh_only is not None or a.nomesh_out):
        ap.error("--from-warmup starts the mesh stage: not with --no-mesh-stage, --mesh-only or --nomesh-out")
    if a.stop_at is not None and a.stop_after is not None:
        ap.error("--stop-at, --stop-after: one or the other")
    if a.stop_after is not None and a.stop_after <= 0:
        ap.error(f"--stop-after {a.stop_after}: seconds, more than 0")
    split_args = a.stop_at is not None or a.stop_after is not None or a.resume
    stopped = None  # the iteration a split stage stopped at
    if split_args and (a.mesh_only is not None or a.nomesh_out):
        ap.error("--stop-at, --stop-after, --resume split a stage's training: not with --mesh-only or --nomesh-out "
                 "(split the warm-up as a --no-mesh-stage run of its own)")
    if a.resume and a.from_warmup:
        ap.error("--resume: the warm-up is the stopped run's (its split.json): not with --from-warmup")
    ex_id = _exchange_id(a.exchange)  # fails before any training on a folder that is not an exchange folder
    split = read_split(a, ex_id) if a.resume else None
    if split:
        a.warmup_iterations = split["warmup_iterations"]
    if a.stop_at is not None:
        views, done_it = len(load(a.exchange).train), split["stopped_at"] if split else 0
        last = stage_of(a)[1]
        if not (done_it < a.stop_at < last) or a.stop_at % views:
            sys.exit(f"--stop-at {a.stop_at}: not a multiple of the {views} training views between the iteration "
                     f"the stage starts from ({done_it}) and its iterations ({last}), both excluded")
    earlier = _earlier_warmup(a.from_warmup, a.out, ex_id) if a.from_warmup else None
    if earlier:
        a.warmup_iterations = earlier["warmup_iterations"]

    head = os.path.abspath(a.checkout)
    init = os.path.abspath(a.init_checkout or os.path.join(os.path.dirname(head), "pgsr_init"))
    # --from-warmup, or a resumed mesh stage, runs no warm-up: its checkout is not needed
    for path, what in ((head, "--checkout"),) + (
            () if earlier or (split and not a.no_mesh_stage) else ((init, "--init-checkout"),)):
        if not os.path.exists(os.path.join(path, "train.py")):
            sys.exit(f"{what}: no train.py in {path}")
    out = os.path.abspath(a.out)
    os.makedirs(out, exist_ok=True)
    src = source_folder(a.exchange, os.path.join(out, "source"))
    warm, model = os.path.join(out, "warmup"), os.path.join(out, "model")
    final, final_ckout = (warm, init) if a.no_mesh_stage else (model, head)
    it = a.mesh_only or (a.warmup_iterations if a.no_mesh_stage else a.iterations)  # the final stage's
    py = sys.executable
    peaks = []

    def peak(name):
        peaks.append(os.path.join(out, f"peak_{name}.json"))
        return [py, os.path.join(HERE, "_peak.py"), peaks[-1]]

    times = {}
    with open(os.path.join(out, "log.txt"), "a") as log:
        t0 = t = time.perf_counter()

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            times[name] = now - t
            t = now

        def stage(prefix, ckout, model_dir, iterations, train=True, more=(), launcher=(), env=None, mesh=True):
            """``train.py`` then ``render.py`` (its TSDF mesh) of one stage, each timed and its peak recorded."""
            if train:
                _run(peak(prefix + "train") + [*launcher, "train.py", "-s", src, "-m", model_dir, *TRAIN_ARGS,
                                               "--test_iterations", "-1", "--iterations", str(iterations), *more],
                     ckout, log, **(env or {}))
                lap(prefix + "train_s")
            if not mesh:
                return
            _run(peak(prefix + "mesh") + ["render.py", "-m", model_dir, *MESH_ARGS, "--iteration", str(iterations)],
                 ckout, log, OMP_NUM_THREADS="4")
            lap(prefix + "mesh_s")

        def trained(prefix, ckout, model_dir, iterations, more=(), launcher=()):
            """A stage's ``train.py`` (under ``_pgsr_split.py`` when split), then its mesh unless it stopped at a
            checkpoint; the iteration it stopped at (--stop-at's, or --stop-after's), None if it trained to the end."""
            more, env = list(more), {}
            if split_args:
                launcher = [os.path.join(HERE, "_pgsr_split.py"), *launcher]
                env["PGSR_SPLIT_TIMES"] = os.path.join(out, "part_times.json")
                if os.path.exists(env["PGSR_SPLIT_TIMES"]):
                    os.remove(env["PGSR_SPLIT_TIMES"])
            if a.stop_at is not None:
                more += ["--checkpoint_iterations", str(a.stop_at)]
                env["PGSR_SPLIT_STOP"] = str(a.stop_at)
            if a.stop_after is not None:
                env["PGSR_SPLIT_STOP_AFTER"] = str(a.stop_after)
                env["PGSR_SPLIT_VIEWS"] = str(len(load(a.exchange).train))
            if split:
                ckpt = os.path.join(model_dir, f"chkpnt{split['stopped_at']}")
                more += ["--start_checkpoint", ckpt + ".pth"]
                env["PGSR_SPLIT_STATE"] = ckpt + "_state.pth"
            launched = time.time()
            stage(prefix, ckout, model_dir, iterations, more=more, launcher=launcher, env=env, mesh=False)
            part = read_json(env["PGSR_SPLIT_TIMES"]) if split_args else {}
            stopped = part.get("stopped_at")
            if a.stop_at is not None and stopped != a.stop_at:
                sys.exit(f"run_pgsr: the stage stopped at {stopped}, not at --stop-at {a.stop_at}")
            if stopped is None:
                stage(prefix, ckout, model_dir, iterations, train=False)
            if split:  # this restart's setup (Python, the scene, the initial mesh, the checkpoint) counts once
                restart = part["first_iteration_at"] - launched
                times[prefix + "train_s"] -= restart
                split["restart_s"].append(restart)
            return stopped

        if a.mesh_only is None:
            if split:
                if not a.no_mesh_stage:
                    shutil.copyfile(os.path.join(out, "mesh_init.ply"), os.path.join(src, "mesh_init.ply"))
                drop_later_app_weights(os.path.join(out, stage_of(a)[0]), split["stopped_at"])
            else:
                shutil.rmtree(model, ignore_errors=True)
            if earlier:
                warm = earlier["dir"]
            elif not split:
                shutil.rmtree(warm, ignore_errors=True)
            if a.no_mesh_stage:  # 1. plain PGSR (de24f1a) and its TSDF mesh: the result
                stopped = trained("warmup_", init, warm, a.warmup_iterations)
            else:
                if not (earlier or split):  # 1. the warm-up, whose TSDF mesh is the mesh stage's start
                    stage("warmup_", init, warm, a.warmup_iterations)
                if not split:  # (a resume put back the stopped run's copy above)
                    shutil.copyfile(os.path.join(warm, "mesh", "tsdf_fusion_post.ply"),
                                    os.path.join(src, "mesh_init.ply"))
                # 2. mesh stage: pgsr_dpsr from the warm-up's mesh
                stopped = trained("", head, model, a.iterations, more=extra,
                                  launcher=[os.path.join(HERE, "_dpsr_cache.py")] if a.cache_dpsr_grids else [])
        else:
            stage("", final_ckout, final, it, train=False)
        wall = time.perf_counter() - t0
        if split:  # the parts before: their time and peak, the warm-up's included
            key = "warmup_train_s" if a.no_mesh_stage else "train_s"
            wall += split["wall_s"] - split["restart_s"][-1]
            times = {**split["times"], **times, key: split["times"][key] + times[key]}
            peaks.append(_peak_file(out, "peak_earlier_parts.json", split["peak_gpu_bytes"]))
            earlier = split["earlier"]
        elif earlier:  # the earlier warm-up's time and peak count in: the whole recipe's figures
            wall += earlier["wall_s"]
            times = {**earlier["times"], **times}
            peaks.append(earlier["peak_json"])
        if stopped is not None:
            write_split(out, a, ex_id, stopped, earlier, split, wall, times,
                        max(read_json(p)["peak_gpu_bytes"] for p in peaks), _device_name())
            return
        done = a.mesh_only is None
        warm_it = a.mesh_only if a.no_mesh_stage and not done else a.warmup_iterations
        split_name = f" [split at {', '.join(f'{i:,}' for i in split['split_at'])}]" if split else ""
        split_run = {"split_at": split["split_at"], "split_restart_s": split["restart_s"],
                     "split_devices": split["devices"]} if split else {}
        if a.no_mesh_stage:
            run = _run_json(warm_it, None, wall if done else None, times if done else {}, peaks if done else None)
            _finish(a.out, a.exchange, ex_id, warm, init, warm_it, log, system=_system(warm_it, None) + split_name,
                    run={**run, **split_run})
        else:
            run = _run_json(a.warmup_iterations, it, wall if done else None, times if done else {},
                            peaks if done else None)
            if extra:
                run["mesh_train_args"] = a.mesh_train_args
            if a.cache_dpsr_grids:
                run["dpsr_grids_cached"] = True
            if earlier:
                run["warmup_from"] = earlier["from"]
                run["warmup_device"] = earlier["device"]
            run.update(split_run)
            system = (_system(a.warmup_iterations, it) + (f" [{a.mesh_train_args}]" if extra else "")
                      + (" [DPSR grids on the GPU]" if a.cache_dpsr_grids else "") + split_name)
            _finish(a.out, a.exchange, ex_id, model, head, it, log, system=system, run=run)
            if earlier and run.get("device") != earlier["device"]:
                print(f"run_pgsr: the warm-up ran on {earlier['device']}, the mesh stage on {run.get('device')}: "
                      "the row's time adds two GPUs' times", file=sys.stderr)
            if a.nomesh_out and done:  # the warm-up alone is plain PGSR: its own result, its own time
                _finish(a.nomesh_out, a.exchange, ex_id, warm, init, warm_it, log, system=_system(warm_it, None),
                        run=_run_json(warm_it, None, times["warmup_train_s"] + times["warmup_mesh_s"],
                                      {k: times[k] for k in ("warmup_train_s", "warmup_mesh_s")}, peaks[:2]))
        if split:  # finished: a later --resume has nothing to go on with
            os.replace(os.path.join(out, "split.json"), os.path.join(out, "split_done.json"))


def _exchange_id(exchange: str) -> str:
    """The exchange folder's name and a digest of its training views' COLMAP cameras and poses: a warm-up carried
    to another machine is checked to be of the same scene at the same resolution."""
    import hashlib

    name = load(exchange).meta["name"]
    h = hashlib.sha1()
    for txt in ("cameras.txt", "images.txt"):
        with open(os.path.join(exchange, "colmap", "sparse", "0", txt), "rb") as f:
            h.update(f.read())
    return f"{name}:{h.hexdigest()[:12]}"


def _earlier_warmup(result: str, out: str, want: str) -> dict:
    """An earlier ``--no-mesh-stage`` run's warm-up on the exchange folder whose ``_exchange_id`` is ``want``, read
    from its result folder ``result``: ``dir`` (its ``warmup`` model folder, holding ``mesh/tsdf_fusion_post.ply``),
    ``warmup_iterations``, ``wall_s``, ``times`` (its training and meshing seconds), ``peak_json`` (its peak GPU
    memory, written under ``out`` in ``_peak.py``'s form), ``device`` (its GPU) and ``from`` (what ran it: its system
    and wall time, for ``run.json``)."""
    run_json = os.path.join(result, "run.json")
    mesh = os.path.join(result, "warmup", "mesh", "tsdf_fusion_post.ply")
    for path in (run_json, mesh):
        if not os.path.isfile(path):
            sys.exit(f"--from-warmup: no {os.path.relpath(path, result)} in {result}")
    run = read_json(run_json)
    if run.get("mesh_stage_iterations") is not None or run.get("wall_s") is None or run.get("peak_gpu_bytes") is None:
        sys.exit(f"--from-warmup: {run_json} is not a whole warm-up's (--no-mesh-stage) result: "
                 f"mesh_stage_iterations={run.get('mesh_stage_iterations')}, wall_s={run.get('wall_s')}, "
                 f"peak_gpu_bytes={run.get('peak_gpu_bytes')}")
    if run.get("exchange") != want:
        sys.exit(f"--from-warmup: {run_json} is a warm-up of exchange={run.get('exchange')!r}, not of {want!r}")
    peak_json = _peak_file(out, "peak_earlier_warmup.json", run["peak_gpu_bytes"])
    return {"dir": os.path.join(result, "warmup"), "warmup_iterations": int(run["warmup_iterations"]),
            "wall_s": float(run["wall_s"]), "peak_json": peak_json,
            "times": {k: float(run[k]) for k in ("warmup_train_s", "warmup_mesh_s")},
            "device": run.get("device"),
            "from": f"an earlier run: {run.get('system')}, {float(run['wall_s']):.0f} s ({os.path.abspath(result)})"}


def _peak_file(out: str, name: str, peak_bytes: int) -> str:
    """An earlier process's peak GPU memory written under ``out`` in ``_peak.py``'s form; its path."""
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, name)
    with open(path, "w") as f:
        json.dump({"peak_gpu_bytes": int(peak_bytes)}, f)
    return path


def _device_name():
    """The GPU this process sees (its training children see the same), or None without one."""
    try:
        import torch
    except ImportError:
        return None
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None


def _system(warmup_it: int, mesh_it) -> str:
    if mesh_it is None:
        return "PGSR (authors', no mesh stage)" if warmup_it == 30_000 else f"PGSR (authors', {warmup_it:,} it.)"
    if (warmup_it, mesh_it) == (30_000, 10_000):
        return "PGSR+DPSR (authors')"
    return f"PGSR+DPSR (authors', {warmup_it:,} + {mesh_it:,} it.)"


def _run_json(warmup_it: int, mesh_it, wall, times: dict, peaks) -> dict:
    """run.json less the surfel count and the held-out renders' peak (``_finish`` adds them).

    ``wall`` / ``peaks`` are None when only an earlier run's checkpoint was meshed (its training's time
    and memory are not known here)."""
    stage = "" if mesh_it is None else f" + pgsr_dpsr {mesh_it:,} it. from that mesh (DPSR proxy mesh from it. 5,000)"
    return {"wall_s": wall, **times,
            "iterations": warmup_it + (mesh_it or 0), "warmup_iterations": warmup_it, "mesh_stage_iterations": mesh_it,
            "_peaks": peaks,
            "recipe": (f"PGSR de24f1a {warmup_it:,} it., its TSDF mesh{stage}; DTU recipe with -r 1 "
                       "--ncc_scale 0.5; TSDF voxel 0.002, truncation 0.008, max depth 5.0, 1 cluster")}


def _finish(out: str, exchange: str, exchange_id: str, model: str, checkout: str, it: int, log, *, system: str,
            run: dict) -> None:
    """Render the held-out views of ``model`` at ``it`` and write the result folder ``out`` (``exchange_id``:
    ``_exchange_id(exchange)``, recorded for a later ``--from-warmup``)."""
    import trimesh

    os.makedirs(out, exist_ok=True)
    views = os.path.join(os.path.abspath(out), "views.npz")
    _run([sys.executable, os.path.join(HERE, "_peer_views.py"), "pgsr", model, str(it), os.path.abspath(exchange),
          views], checkout, log)
    mesh = trimesh.load(os.path.join(model, "mesh", "tsdf_fusion_post.ply"), process=False)
    v = np.load(views)
    peaks = run.pop("_peaks")
    run["surfels"] = int(v["n"])
    run["exchange"] = exchange_id
    run["device"] = _device_name()
    # the processes' peaks (training, meshing, held-out renders); unknown for an earlier run's training
    gpu = [read_json(p)["peak_gpu_bytes"] for p in peaks or () if os.path.exists(p)] + [int(v["peak"])]
    run["peak_gpu_bytes"] = None if peaks is None else max(gpu)
    write_result(out, system=system, mesh=mesh, renders=v["rgb"].astype(np.float32), run=run)

if __name__ == "__main__":
    main()
