# SPDX-License-Identifier: Apache-2.0
"""Benchmark of ``wtopo.fit`` on a built-in scene (the bunny by default), with an ablation table.

Measures, per variant and seed: wall time and process CPU time (less sensitive to other jobs on
shared cores; the fit uses up to 2 threads, so CPU time can exceed wall time) of the whole fit
(kernel compilation included when the Warp cache is cold), Chamfer distance and F-score at 0.5 %
of the ground truth's bounding-box diagonal (uniform surface samples), PSNR on the held-out views
(inside the masks for a masked scene, as the fit reports it), watertightness and component count. The
peer measured in the same process is the TSDF fusion of the *ground-truth* depth maps of the training
views on the final mesh's grid (the upper bound of image-based fitting at that resolution,
design/overview.md); each variant's Chamfer is printed as a ratio to it.

Variants: ``full`` (defaults); ``no_mesh_loop`` (co-evolution iterations without the proxy
mesh); ``view_flips`` (normal signs from view directions only); ``random_flips``; ``no_geo_density``
(no geometry-aware prune / densification); ``one_point`` (1 oriented point per surfel instead of 5);
``filter_2dgs`` (the renderer's low-pass at 2DGS's 0.71 px instead of 0.35 px); ``mask_05``
(mask weight 0.5 instead of 0.2).

Command (writes benchmarks/fit.md)::

    .venv/bin/python benchmarks/bench_fit.py --out benchmarks/fit.md
    .venv/bin/python benchmarks/bench_fit.py --variants full --seeds 0 1   # subset
    python benchmarks/bench_fit.py --variants full no_mesh_loop --views 64 --image-size 512 \
        --mesh-resolution 256 --device cuda:0 --out gpu_fit.md              # GPU settings
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np
import torch

from wtopo import scenes
from wtopo.fitting import FitConfig, fit
from wtopo.fitting.evaluate import F_SCORE_TAU, geometry_metrics
from wtopo.fitting.loop import _resolve_device
from wtopo.fitting.plan import make_plan
from wtopo.fitting.stages import TRUNCATION_VOXELS
from wtopo.fitting.tsdf import auto_bounds, cleanup_mesh, fuse_depths

# variant -> FitConfig overrides (``wtopo fit --set`` syntax)
VARIANTS = {
    "full": (),
    "no_mesh_loop": ("coevolution.enabled=false",),
    "view_flips": ("mesh.normal_flip=view",),
    "random_flips": ("mesh.normal_flip=random",),
    "no_geo_density": ("densify.geometry_prune=false", "densify.geometry_densify=false"),
    "one_point": ("mesh.samples_per_surfel=1",),
    "filter_2dgs": (f"filter_sigma={2.0 ** -0.5}",),
    "mask_05": ("losses.mask=0.5",),
}


def gt_depth_peer(scene, device: str = "auto") -> dict:
    """TSDF fusion of the ground-truth depth maps of the training views (the upper bound), on the grid the
    default plan gives the fit's final mesh on ``device``."""
    sim = scene.normalization()
    internal = scene.normalized()
    train = internal.split("train")
    t = time.perf_counter()
    resolution = make_plan(internal, FitConfig(), _resolve_device(device)).final_resolution
    b = auto_bounds(torch.as_tensor(np.asarray(internal.gt_mesh.vertices)), None,
                    resolution=resolution, truncation_voxels=TRUNCATION_VOXELS)
    mesh = fuse_depths(train.cameras, [d.cpu().numpy() for d in train.depths],
                       [i.cpu().numpy() for i in train.images], b)
    mesh = sim.to_world(cleanup_mesh(mesh))
    g = geometry_metrics(mesh, scene.gt_mesh)
    return {"time": time.perf_counter() - t, **g}


def run_variant(scene, name: str, seed: int, iterations: int | None, device: str = "auto",
                mesh_resolution: int | None = None, sets=()) -> dict:
    from wtopo.cli import _apply_set

    cfg = FitConfig()
    for item in (*sets, *VARIANTS[name]):  # --set overrides first: a variant's own change wins
        _apply_set(cfg, item)
    cfg.runtime.seed = seed
    cfg.runtime.usd_every = 0
    cfg.runtime.device = device
    if mesh_resolution is not None:
        cfg.mesh.resolution = mesh_resolution
    if iterations is not None:
        # the plan's budgets split every preset's iterations in half between the two stages
        cfg.warmup.iterations, cfg.coevolution.iterations = iterations // 2, iterations - iterations // 2
    t, c = time.perf_counter(), time.process_time()
    res = fit(scene, cfg, progress=False)
    elapsed, cpu = time.perf_counter() - t, time.process_time() - c
    g = geometry_metrics(res.mesh, scene.gt_mesh, seed=seed)
    comps = len(res.mesh.split(only_watertight=False)) if len(res.mesh.faces) else 0
    return {"variant": name, "seed": seed, "time": elapsed, "cpu": cpu, "chamfer_rel": g["chamfer_rel"],
            "f_score": g["f_score"],
            "psnr": res.report.get("psnr", float("nan")), "watertight": bool(res.mesh.is_watertight),
            "components": comps, "surfels": len(res.surfels), "stage_times": res.report["stage_times_s"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="bunny")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--iterations", type=int, help="total iterations (default: the FitConfig defaults)")
    ap.add_argument("--out", help="markdown file to write the table to")
    ap.add_argument("--views", type=int, help="training views of the scene (default: the scene's)")
    ap.add_argument("--image-size", type=int, help="image side in pixels (default: the scene's)")
    ap.add_argument("--mesh-resolution", type=int, help="co-evolution Poisson grid (default: FitConfig's)")
    ap.add_argument("--device", default="auto", help="FitConfig.runtime.device (auto, cpu, cuda:0)")
    ap.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                    help="FitConfig override applied to every variant (as `wtopo fit --set`)")
    args = ap.parse_args(argv)

    load0 = os.getloadavg()[0]
    kw = {}
    if args.views is not None:
        kw["n_views"] = args.views
    if args.image_size is not None:
        kw["resolution"] = args.image_size
    scene = scenes.load(args.scene, **kw)
    peer = gt_depth_peer(scene, args.device)
    print(f"peer (TSDF of ground-truth depth): Chamfer {100 * peer['chamfer_rel']:.3f} % of diagonal, "
          f"F-score {peer['f_score']:.3f}", flush=True)
    rows = []
    for name in args.variants:
        for seed in args.seeds:
            r = run_variant(scene, name, seed, args.iterations, args.device, args.mesh_resolution, args.set)
            rows.append(r)
            print(f"{name:15s} seed {seed}: {r['time']:6.1f} s (cpu {r['cpu']:.1f} s)  "
                  f"Chamfer {100 * r['chamfer_rel']:.3f} % "
                  f"({r['chamfer_rel'] / peer['chamfer_rel']:.1f}x peer)  F {r['f_score']:.3f}  PSNR {r['psnr']:.2f}  "
                  f"watertight {r['watertight']}  components {r['components']}", flush=True)
    load1 = os.getloadavg()[0]
    if args.out:
        lines = [
            f"# wtopo.fit on the `{args.scene}` scene",
            "",
            "Command: `python benchmarks/bench_fit.py "
            f"{' '.join(argv if argv is not None else sys.argv[1:])}`",
            "",
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
            f"{load0:.1f} at start and {load1:.1f} at end (the cores are shared: times are noisy); "
            f"torch {torch.__version__}.",
            "",
            f"Peer in the same process: TSDF fusion of the ground-truth depth maps: Chamfer "
            f"{100 * peer['chamfer_rel']:.3f} % of the bbox diagonal, F-score {peer['f_score']:.3f}.",
            f"F-score at {100 * F_SCORE_TAU:.1f} % of the diagonal; PSNR on the held-out views, inside the masks "
            "for a masked scene.",
            "",
            "| variant | seed | wall [s] | process CPU [s] | Chamfer [% diag] | x peer | F-score | PSNR [dB] "
            "| watertight | components | surfels |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            lines.append(f"| {r['variant']} | {r['seed']} | {r['time']:.1f} | {r['cpu']:.1f} | "
                         f"{100 * r['chamfer_rel']:.3f} | "
                         f"{r['chamfer_rel'] / peer['chamfer_rel']:.1f} | {r['f_score']:.3f} | {r['psnr']:.2f} | "
                         f"{r['watertight']} | {r['components']} | {r['surfels']} |")
        lines += ["", "Stage times of the first row [s]: " +
                  ", ".join(f"{k} {v:.1f}" for k, v in rows[0]["stage_times"].items()), ""]
        with open(args.out, "w") as f:
            f.write("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
