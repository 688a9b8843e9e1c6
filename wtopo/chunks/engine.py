# SPDX-License-Identifier: Apache-2.0
"""``wtopo.chunks.fit_chunked``: fit a large scene chunk by chunk, on one or several processes.

The engine is ``torch.distributed`` (one process per GPU, launched by ``torchrun``): each rank fits
the chunks ``i`` with ``i % world_size == rank`` on ``cuda:<local_rank>`` (or the CPU), writes each
chunk's result atomically to ``out_dir/chunks/<i>/``, waits at a barrier, and rank 0 merges. Without
an initialised process group the same code runs every chunk one after another in this process.
Several machines: torchrun's multi-node rendezvous (``--nnodes``, ``--rdzv-endpoint``) with
``out_dir`` on a shared file system; nothing else changes.

Resumable: a chunk whose result directory exists is not fitted again, and an interrupted chunk
resumes from the fit's own checkpoints in ``out_dir/chunks/<i>.partial/``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..io._common import atomic_write
from .merge import boundary_edges_near, merge_meshes, merge_surfels, refuse_mesh, refuse_resolution
from .partition import ChunkConfig, ChunkPlan, plan_chunks

__all__ = ["fit_chunked", "ChunkedResult", "chunk_scene", "chunk_fit_config", "rank_chunks", "dist_info", "cuda_peak"]


@dataclass
class ChunkedResult:
    """What :func:`fit_chunked` returns on rank 0.

    Attributes:
        mesh: the merged mesh, world (the caller's) frame.
        plan: the :class:`~.partition.ChunkPlan`.
        report: timings (per chunk, fit wall clock, merge), peak memory per rank, the merge's record
            (``"merge"``: method, open edges near the cuts, and the re-fusion's voxel or the weld counts).
    """

    mesh: trimesh.Trimesh
    plan: ChunkPlan
    report: dict = field(default_factory=dict)


def dist_info() -> tuple[int, int, int]:
    """``(rank, world_size, local_rank)`` of an initialised ``torch.distributed`` group, else ``(0, 1, 0)``."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", dist.get_rank()))
    return 0, 1, 0


def rank_chunks(n_chunks: int, rank: int, world_size: int) -> list[int]:
    """The chunk indices rank ``rank`` of ``world_size`` fits: ``i % world_size == rank``."""
    if world_size < 1 or not (0 <= rank < world_size):
        raise ValueError(f"rank must be in [0, world_size), got rank={rank}, world_size={world_size}")
    return [i for i in range(n_chunks) if i % world_size == rank]


def chunk_scene(scene, chunk):
    """``scene`` restricted to ``chunk``'s cameras, with ``bounds`` = the chunk's box and the
    scene's points inside that box; the ground-truth mesh is dropped (the merged mesh is measured,
    not the chunks)."""
    sub = scene.subset(chunk.cameras)
    pts = {}
    if sub.points is not None:
        inside = np.all((sub.points >= chunk.lower) & (sub.points <= chunk.upper), axis=1)
        pts = {"points": sub.points[inside] if inside.any() else None,
               "point_colors": None if sub.point_colors is None or not inside.any() else sub.point_colors[inside]}
    if sub.test_indices is not None and len(sub.test_indices) == 0:  # no held-out view sees the chunk
        sub = sub.subset(sub.train_indices)
        sub = dataclasses.replace(sub, train_indices=None, test_indices=None)
    return dataclasses.replace(sub, bounds=(chunk.lower.copy(), chunk.upper.copy()), gt_mesh=None,
                               name=f"{scene.name}#chunk{chunk.index}", **pts)


def _rank_device(requested: str, local_rank: int, world_size: int) -> str:
    import torch

    if requested == "cpu" or not torch.cuda.is_available():
        return "cpu"
    if world_size > 1 or requested in ("auto", "cuda"):
        return f"cuda:{local_rank % torch.cuda.device_count()}"
    return requested


def _write_json(path: Path, data) -> None:
    text = json.dumps(data, indent=1, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def chunk_fit_config(cfg, device: str, share: float, space: float = 1.0, budget: tuple[int, int] | None = None):
    """A copy of ``cfg`` on ``device`` whose warm-up and co-evolution iterations are ``share`` of the
    budget and whose point budgets (initial points, surfel cap, re-initialisation faces, background
    points when set) are ``space`` of theirs (the configured values, or the plan's for the device
    when left to it). ``budget``: the whole scene's planned ``(warm-up, co-evolution)`` iterations
    (:func:`wtopo.fitting.iteration_budget`) for those the configuration leaves to the plan;
    ``None``: the device's base budget."""
    import copy

    from ..fitting import plan_defaults

    c = copy.deepcopy(cfg)
    c.runtime.device = device
    base = plan_defaults(device, cfg.preset)
    if space < 1.0:
        cap = cfg.runtime.max_surfels or base.max_surfels
        faces = cfg.tsdf.max_faces or base.reinit_faces
        c.runtime.max_surfels = max(1, round(space * cap))
        c.tsdf.max_faces = max(1, round(space * faces))
        c.init.num_points = max(1, round(space * cfg.init.num_points))
        if cfg.init.background_points:
            c.init.background_points = max(1, round(space * cfg.init.background_points))
    warm, coevo = base.iterations if budget is None else budget
    warm = warm if cfg.warmup.iterations is None else cfg.warmup.iterations
    coevo = coevo if cfg.coevolution.iterations is None else cfg.coevolution.iterations
    c.warmup.iterations = max(1, round(share * warm)) if warm else 0
    c.coevolution.iterations = max(1, round(share * coevo)) if coevo else 0
    if cfg.polish.iterations is not None:  # the plan's polish follows the chunk's co-evolution by itself
        c.polish.iterations = round(share * cfg.polish.iterations)
    return c


def _fit_one(scene, plan: ChunkPlan, index: int, cfg, ccfg: ChunkConfig, out: Path, device: str, rank: int,
             progress: bool) -> dict:
    import torch

    from ..fitting import fit, fit_surfels, iteration_budget

    final, partial = out / "chunks" / str(index), out / "chunks" / f"{index}.partial"
    if (final / "chunk.json").exists():
        return json.loads((final / "chunk.json").read_text()) | {"resumed": True}
    chunk = plan.chunks[index]
    train = range(len(scene)) if scene.train_indices is None else scene.train_indices
    share = space = 1.0
    if ccfg.iteration_share:
        share = max(ccfg.min_budget_share, len(set(chunk.cameras) & {int(i) for i in train}) / len(train))
    if ccfg.space_share:
        space = max(ccfg.min_budget_share, min(1.0, chunk.volume_share(plan.roi_lower, plan.roi_upper)))
    # the share of what the whole scene's fit would run (the plan scales a CPU budget with the pixels to fit)
    budget = iteration_budget(scene, torch.device(device), cfg.runtime.image_scale, cfg.preset)[:2]
    c = chunk_fit_config(cfg, device, share, space, budget)
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)
    t = time.perf_counter()
    fitter = fit if ccfg.builds_chunk_meshes() else fit_surfels  # the re-fusing merge throws the chunk's mesh away
    res = fitter(chunk_scene(scene, chunk), c, out_dir=partial, progress=progress)
    if res.report["status"] != "completed":  # interrupted: its checkpoints stay, a rerun resumes it
        raise RuntimeError(f"the fit stopped with status {res.report['status']!r}; a rerun resumes it from {partial}")
    info = {"index": index, "rank": rank, "device": device, "seconds": round(time.perf_counter() - t, 3),
            "views": len(chunk.cameras), "iteration_share": round(share, 4), "space_share": round(space, 4),
            "iterations": [c.warmup.iterations, c.coevolution.iterations], "faces": int(len(res.mesh.faces)),
            "final_s": round(float(res.report.get("stage_times_s", {}).get("final", 0.0)), 3),
            "status": res.report["status"], **(cuda_peak(device) if cuda else {"peak_memory_bytes": None})}
    _write_json(partial / "chunk.json", info)
    if final.exists():  # a stale, incomplete result (no chunk.json): replaced
        shutil.rmtree(final)
    os.replace(partial, final)  # the result appears at once, complete
    return info


def cuda_peak(device: str) -> dict:
    """Peak device memory of this process on ``device``: torch's allocator since its last reset
    (``torch.cuda.max_memory_allocated``) and Warp's memory-pool high-water mark
    (``wp.get_mempool_used_mem_high``, which cannot be reset: the process's peak so far); their sum
    is ``peak_memory_bytes``."""
    import torch
    import warp as wp

    t = int(torch.cuda.max_memory_allocated(device))
    try:
        w = int(wp.get_mempool_used_mem_high(device))
    except (RuntimeError, ValueError):  # no memory pool on this device: Warp allocations are not counted
        w = 0
    return {"peak_memory_bytes": t + w, "torch_peak_bytes": t, "warp_pool_high_bytes": w}


def _peak_rss() -> int:
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # Linux reports KiB


def _merge(out: Path, plan: ChunkPlan, ccfg: ChunkConfig, scene, cfg, device: str) -> tuple[trimesh.Trimesh, dict]:
    from ..io import export_mesh
    from ..io.ply import read_surfels_ply, write_surfels_ply

    meshes, surfels, resolutions = {}, {}, {}
    for ch in plan.chunks:
        d = out / "chunks" / str(ch.index)
        if ch.skipped or not (d / "chunk.json").exists():
            continue
        if ccfg.merge == "weld":
            meshes[ch.index] = trimesh.load(d / "mesh.ply", process=False, force="mesh")
            if len(meshes[ch.index].faces) == 0 and json.loads((d / "chunk.json").read_text()).get("faces") == 0:
                raise RuntimeError(f"chunk {ch.index} in {d} was fitted without its own mesh (a re-fusing run); "
                                   "merge='weld' needs it: remove the directory to fit the chunk again")
        if (d / "surfels.ply").exists():
            surfels[ch.index] = read_surfels_ply(d / "surfels.ply")
        resolutions[ch.index] = int(json.loads((d / "config.json").read_text())["final"]["resolution"])
    merged = merge_surfels(surfels, plan) if surfels else None
    if ccfg.merge == "weld":
        mesh, info = merge_meshes(meshes, plan, fraction=ccfg.weld_fraction)
        info["method"] = "weld"
    else:
        if merged is None:
            raise RuntimeError(f"no chunk left surfels in {out / 'chunks'}: nothing to re-fuse")
        mesh, info = refuse_mesh(scene, merged, cfg, resolution=refuse_resolution(plan, resolutions), device=device,
                                 plan=plan)
    band = [ccfg.overlap * float(plan.roi_upper[a] - plan.roi_lower[a]) / plan.grid[a] for a, _ in plan.cuts()]
    info["open_edges_near_cuts"] = sum(boundary_edges_near(mesh, [c], w) for c, w in zip(plan.cuts(), band))
    info["band"] = band
    export_mesh(mesh, out / "mesh.ply")
    if merged is not None:
        write_surfels_ply(out / "surfels.ply", *merged)
        info["surfels"] = int(len(merged[0]))
    return mesh, info


def _gather(obj, world: int) -> list:
    import torch.distributed as dist

    if world == 1:
        return [obj]
    out = [None] * world
    dist.all_gather_object(out, obj)
    return out


def fit_chunked(scene, out_dir: str | os.PathLike, config=None, *, chunk_config: ChunkConfig | None = None,
                progress: bool = True) -> ChunkedResult | None:
    """Fit ``scene`` as overlapping chunks and merge them into one mesh (see the module docstring).

    The merge is ``chunk_config.merge``: ``"refuse"`` (default) meshes the chunks' merged core surfels
    once over the whole region of interest with the fit's own final meshing on rank 0's device
    (:func:`~.merge.refuse_mesh`; the chunks' fits then skip their own final mesh), ``"weld"`` welds
    the chunks' own meshes at the cuts (:func:`~.merge.merge_meshes`).

    Under ``torchrun`` (an initialised ``torch.distributed`` process group) every rank calls this
    with the same scene and configuration; rank 0 plans, the plan is broadcast, each rank fits its
    chunks, and rank 0 merges. Files in ``out_dir``: ``chunk_plan.json``, ``chunks/<i>/`` (each
    chunk's :func:`wtopo.fit` outputs and ``chunk.json``), ``mesh.ply``, ``surfels.ply`` (world
    frame) and ``report.json`` (wall clock, per-chunk seconds, peak memory per rank: on CUDA torch's
    ``max_memory_allocated`` plus Warp's memory-pool high-water mark, :func:`cuda_peak`; on CPU the
    process's peak resident set).

    Args:
        scene: a :class:`wtopo.Scene` (world frame); its region of interest is partitioned.
        out_dir: run directory (required: chunks are exchanged through it).
        config: the :class:`wtopo.FitConfig` every chunk runs (``None``: defaults).
        chunk_config: :class:`~.partition.ChunkConfig` (``None``: the plan decides the count).
        progress: print the plan and each chunk's progress.

    Returns:
        :class:`ChunkedResult` on rank 0, ``None`` on the other ranks.

    Raises:
        TypeError: ``scene``, ``config`` or ``chunk_config`` of the wrong type.
        ValueError: ``out_dir`` is None; a bad configuration; no chunk has enough views.
        RuntimeError: a chunk's fit failed (on every rank; the message names the chunk and the error).
    """
    from ..fitting import FitConfig, validate_config
    from ..scene import Scene

    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a wtopo.Scene, got {type(scene).__name__}")
    if out_dir is None:
        raise ValueError("out_dir must be a directory path for a chunked fit (chunks are written there), got None")
    cfg = FitConfig() if config is None else config
    if not isinstance(cfg, FitConfig):
        raise TypeError(f"config must be a wtopo.FitConfig or None, got {type(cfg).__name__}")
    validate_config(cfg)
    ccfg = ChunkConfig() if chunk_config is None else chunk_config
    if not isinstance(ccfg, ChunkConfig):
        raise TypeError(f"chunk_config must be a wtopo.chunks.ChunkConfig or None, got {type(ccfg).__name__}")
    ccfg.validate()  # on every rank: each reads the merge settings
    rank, world, local = dist_info()
    out = Path(out_dir)
    t0 = time.perf_counter()
    plan = [None]
    if rank == 0:
        try:
            plan[0] = plan_chunks(scene, ccfg, fit_config=cfg, world_size=world)
        except (TypeError, ValueError) as e:  # every rank raises it, none waits for a plan that never comes
            plan[0] = e
    if world > 1:
        import torch.distributed as dist

        dist.broadcast_object_list(plan, src=0)
    plan = plan[0]
    if isinstance(plan, Exception):
        raise plan
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        _write_json(out / "chunk_plan.json", plan.to_dict())
        if progress:
            print(f"wtopo chunks: {len(plan.chunks)} chunks, grid {plan.grid}: {plan.reason}", flush=True)
    device = _rank_device(str(cfg.runtime.device), local, world)
    if device.startswith("cuda"):  # default devices too, for any allocation that names none
        import torch
        import warp as wp

        torch.cuda.set_device(device)
        wp.set_device(device)
    mine = [i for i in rank_chunks(len(plan.chunks), rank, world) if not plan.chunks[i].skipped]
    infos = []
    for i in mine:
        try:
            infos.append(_fit_one(scene, plan, i, cfg, ccfg, out, device, rank, progress))
        except Exception as e:  # noqa: BLE001 - reported on every rank after the gather, so none waits forever
            infos.append({"index": i, "rank": rank, "error": f"{type(e).__name__}: {e}"})
            break
    peak = max((i.get("peak_memory_bytes") or 0 for i in infos), default=0) if device.startswith("cuda") else None
    mine_report = {"rank": rank, "device": device, "chunks": mine, "peak_memory_bytes": peak,
                   "peak_rss_bytes": _peak_rss(), "fit_seconds": round(time.perf_counter() - t0, 3)}
    ranks = _gather({"rank": mine_report, "chunks": infos}, world)  # also the barrier: every rank is done
    failed = [c for r in ranks for c in r["chunks"] if "error" in c]
    if failed:
        raise RuntimeError("chunked fit failed: " + "; ".join(f"chunk {c['index']} (rank {c['rank']}): {c['error']}"
                                                              for c in failed) + f"; finished chunks stay in {out}")
    if rank != 0:
        return None
    t_fit = time.perf_counter() - t0
    t = time.perf_counter()
    mesh, merge_info = _merge(out, plan, ccfg, scene, cfg, device)
    report = {"chunks": len(plan.chunks), "grid": list(plan.grid), "reason": plan.reason, "world_size": world,
              "fit_wall_s": round(t_fit, 3), "merge_s": round(time.perf_counter() - t, 3),
              "wall_s": round(time.perf_counter() - t0, 3),
              "per_chunk": sorted((c for r in ranks for c in r["chunks"]), key=lambda c: c["index"]),
              "per_rank": [r["rank"] for r in ranks],
              "skipped": {c.index: c.skipped for c in plan.chunks if c.skipped},
              "merge": merge_info, "mesh": {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}}
    _write_json(out / "report.json", report)
    if progress:
        print(f"wtopo chunks: merged {len(mesh.faces)} faces in {report['wall_s']:.1f} s "
              f"({world} process{'es' if world > 1 else ''})", flush=True)
    return ChunkedResult(mesh, plan, report)
