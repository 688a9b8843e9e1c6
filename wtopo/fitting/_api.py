# SPDX-License-Identifier: Apache-2.0
"""``wtopo.fit``: posed images in, a watertight mesh in the caller's frame out."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..geometry.components import face_components
from ..geometry.winding import is_closed
from ..io._common import atomic_write
from .checkpoint import versions
from .config import FitConfig, PolishConfig, config_hash
from .evaluate import geometry_metrics
from .loop import FitRun
from .plan import Plan
from .profiling import format_profile
from .surfels import Surfels
from .validate_config import validate_config

__all__ = ["fit", "fit_surfels", "FitResult"]


@dataclass
class FitResult:
    """What :func:`fit` returns.

    Attributes:
        mesh: the final mesh, in the scene's (the caller's) frame.
        surfels: the fitted surfels, in the internal frame (``report["normalization"]`` maps them back;
            ``surfels.ply`` in ``out_dir`` holds them in the caller's frame). Render them with the screen-space
            filter they were fitted with, ``RasterConfig(filter_sigma=plan.filter_sigma)`` (by default 0.25 px on CUDA,
            0.35 on the CPU): the rasterizer's own default, 2DGS's 0.71 px, blurs them.
        plan: the stage plan (:class:`~wtopo.fitting.plan.Plan`): ``print(result.plan)`` says which stages
            ran and why; ``plan.json`` in ``out_dir`` is its :meth:`~wtopo.fitting.plan.Plan.to_dict`.
        history: one record per evaluation (iteration, stage, elapsed, stage_times, losses,
            surfels, proxy_faces, held-out psnr / ssim and, with a ground-truth mesh, chamfer / f_score).
        report: summary (status, times, counts, final metrics, mesh statistics, versions; with
            ``runtime.profile`` the per-stage time table, ``"profile"``, :meth:`~.profiling.Timers.profile`).
    """

    mesh: trimesh.Trimesh
    surfels: Surfels
    plan: Plan
    history: list[dict]
    report: dict = field(default_factory=dict)


def _atomic_json(path: Path, data) -> None:
    text = json.dumps(data, indent=1, default=_json_default)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _components(mesh: trimesh.Trimesh) -> int:
    """Number of connected components (faces sharing a vertex; :func:`~wtopo.geometry.components.face_components`)."""
    return face_components(np.asarray(mesh.faces), len(mesh.vertices))[0]


def _report(run: FitRun, mesh_world: trimesh.Trimesh, scene) -> dict:
    final = run.history[-1] if run.history else {}
    rep = {
        "status": run.status,
        "iterations": run.it,
        "elapsed_s": round(run.elapsed(), 3),
        "stage_times_s": {k: round(v, 3) for k, v in run.timers.total.items()},
        "surfels": len(run.surfels),
        "proxy_faces": 0 if run.proxy_mesh is None else run.proxy_mesh.num_faces,
        "mesh": {"vertices": int(len(mesh_world.vertices)), "faces": int(len(mesh_world.faces)),
                 "watertight": is_closed(mesh_world.faces),
                 "components": _components(mesh_world)},
        "non_finite_steps": run.total_failures,
        "device": str(run.device),
        "normalization": {"scale": run.sim.scale, "translation": list(run.sim.translation)},
        "tsdf": run.tsdf_info,
        "coevolution": run.coevolution_info,
        "config_hash": run.hash,
        "versions": versions(),
        "events": run.events[-50:],
    }
    rep["scene_kind"] = run.cfg.kind.value
    # the surfels' and the mesh's figures from the final evaluation (after the polish, when one ran)
    made = next((r for r in reversed(run.history) if r.get("stage") == "final"), final)
    for k in ("psnr", "ssim", "psnr_on", "image_metrics_on"):
        if k in final:
            rep[k] = final[k]
    for k in ("chamfer", "f_score", "accuracy", "completeness"):
        if k in made:
            rep[k] = made[k]
    if getattr(scene, "gt_mesh", None) is not None and len(mesh_world.faces):
        g = geometry_metrics(mesh_world, scene.gt_mesh, seed=run.cfg.runtime.seed)
        rep["chamfer_world"] = g["chamfer"]
    return rep


def summary_metrics(report: dict) -> str:
    """The quality figures of a run's ``report`` as a sentence tail for the one-line summary."""
    out = ""
    if "psnr" in report:
        on = "held-out" if report.get("image_metrics_on", "held_out") == "held_out" else "training-view"
        inside = " inside the masks" if report.get("psnr_on") == "masks" else ""
        out += f", {on} PSNR{inside} {report['psnr']:.2f} dB, SSIM {report.get('ssim', float('nan')):.3f}"
    if "chamfer" in report:
        out += f", Chamfer {100 * report['chamfer']:.3f} % of diagonal, F-score {report['f_score']:.3f}"
    return out


def _finish(run: FitRun, mesh_int: trimesh.Trimesh, scene, out_dir) -> FitResult:
    """The result in the caller's frame, its report and (with ``out_dir``) its files, timed as the ``"outputs"``
    section; with ``runtime.profile`` the report's profile spans the whole fit, every file but ``report.json``
    itself included (the report's ``stage_times_s`` is taken inside that section, without it)."""
    with run.timers("outputs"):
        mesh = run.sim.to_world(mesh_int)
        result = FitResult(mesh=mesh, surfels=run.surfels, plan=run.plan, history=run.history)
        result.report = _report(run, mesh, scene)
        if out_dir is not None:
            _write_outputs(Path(out_dir), result, run)
    if run.cfg.runtime.profile:
        result.report["profile"] = run.timers.profile(time.perf_counter() - run.t_start)
    if out_dir is not None:
        _atomic_json(Path(out_dir) / "report.json", result.report)
    return result


def _write_outputs(out: Path, result: FitResult, run: FitRun) -> None:
    """Every file of a run directory but ``report.json`` (:func:`_finish` writes it last)."""
    from ..io import export_mesh, write_surfels_ply

    out.mkdir(parents=True, exist_ok=True)
    export_mesh(result.mesh, out / "mesh.ply")
    s, sim = result.surfels, run.sim
    write_surfels_ply(out / "surfels.ply", sim.to_world(s.means.detach().cpu().double().numpy()),
                      s.quats.detach().cpu().numpy(), sim.length_to_world(s.scales.detach().cpu().double().numpy()),
                      s.opacities.detach().cpu().numpy(), s.sh.detach().cpu().numpy())
    _atomic_json(out / "history.json", result.history)
    _atomic_json(out / "plan.json", result.plan.to_dict())
    _atomic_json(out / "config.json", run.cfg.to_dict())


def fit(scene, config: FitConfig | None = None, *, out_dir: str | os.PathLike | None = None,
        progress: bool = True) -> FitResult:
    """Fit Gaussian surfels co-evolving with a proxy mesh to ``scene`` and return a watertight mesh.

    Stages: initialisation (scene points or the cameras' common volume), photometric warm-up with
    density control, TSDF re-initialisation, co-evolution with the differentiable proxy mesh
    (oriented points -> Poisson -> marching cubes -> ray cast; mesh-depth and mesh-normal losses),
    after a proxy-mesh loop a photometric polish of the surfels, then a final TSDF fusion of their rendered
    depth. A stage plan decided from the scene says which parts
    run and why (printed at the start, ``result.plan``).

    With ``out_dir``, checkpoints are written atomically to ``out_dir/checkpoints`` and a run that
    finds checkpoints of the same configuration there resumes where it stopped. SIGINT / SIGTERM
    finish the current step, checkpoint and return the results so far (``report["status"] ==
    "interrupted"``). Files: ``mesh.ply``, ``surfels.ply`` (3DGS layout), ``history.json``,
    ``report.json``, ``plan.json``, ``config.json`` and, with ``runtime.usd_every``,
    ``timeline.usdc``.

    Args:
        scene: a :class:`wtopo.Scene` (world frame, any scale and offset).
        config: :class:`FitConfig`; ``None`` for the defaults.
        out_dir: run directory, or ``None`` for no files.
        progress: print the plan and show progress bars.

    Returns:
        :class:`FitResult`.

    Raises:
        TypeError: ``scene`` is not a Scene or ``config`` not a FitConfig.
        ValueError: ``out_dir`` holds checkpoints of another configuration.
        wtopo.fitting.loop.FitAborted: too many consecutive non-finite steps (checkpoint written).

    References:
        Fan et al., "TopoSurfel" (2026); Huang et al., "2D Gaussian Splatting" (SIGGRAPH 2024);
        Peng et al., "Shape As Points" (NeurIPS 2021).

    Limitations:
        Surfels are 2D Gaussians and the proxy uses plain marching cubes (no dual MC).
    """
    from ..scene import Scene

    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a wtopo.Scene, got {type(scene).__name__}")
    cfg = FitConfig() if config is None else config
    if not isinstance(cfg, FitConfig):
        raise TypeError(f"config must be a wtopo.FitConfig or None, got {type(cfg).__name__}")
    validate_config(cfg)
    run = FitRun(scene, cfg, out_dir, progress)
    result = _finish(run, run.run(), scene, out_dir)
    if progress and cfg.runtime.progress:
        r = result.report
        line = (f"wtopo fit {r['status']}: {r['iterations']} iterations, {r['elapsed_s']:.1f} s, "
                f"{r['mesh']['faces']} faces")
        print(line + summary_metrics(r))
    if cfg.runtime.profile:
        print(format_profile(result.report["profile"]))
    return result


class _NoFinalMesh(FitRun):
    """A fit whose final stage returns an empty mesh (:func:`fit_surfels`)."""

    def _final_mesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)


def fit_surfels(scene, config: FitConfig, *, out_dir: str | os.PathLike, progress: bool = True) -> FitResult:
    """:func:`fit` without its final mesh: the surfels are the result (a chunk of :mod:`wtopo.chunks` whose
    mesh the merge re-fuses from the merged surfels, ``ChunkConfig.merge = "refuse"``).

    Every stage but the final meshing and the polish runs as in :func:`fit` (resumable from the same checkpoints);
    ``result.mesh`` is empty and ``out_dir`` gets the same files (``mesh.ply`` empty).

    Args:
        scene: a :class:`wtopo.Scene` (world frame).
        config: a validated :class:`wtopo.FitConfig`.
        out_dir: run directory (required: the merge reads ``surfels.ply`` and ``config.json`` there).
        progress: print the plan and show progress bars.

    Returns:
        :class:`FitResult` with an empty ``mesh``.
    """
    # no polish: the merge fuses its mesh from these surfels as the mesh loop left them (a chunk's polish was never
    # measured against the merged mesh); the hash
    # is the configuration's own, so a chunk directory of `fit` or of an earlier version resumes
    run = _NoFinalMesh(scene, dataclasses.replace(config, polish=PolishConfig(iterations=0)), out_dir, progress)
    run.hash = config_hash(config)
    return _finish(run, run.run(), scene, out_dir)
