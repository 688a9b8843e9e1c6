# SPDX-License-Identifier: Apache-2.0
"""The final watertight re-mesh (``wtopo.fitting._final_mesh.poisson_remesh``) on the fit's device against the CPU.

A CUDA fit's final mesh is fused at ``final.resolution`` (up to 768^3 at 512-px photographs); when it is not
closed the fit re-meshes it by Poisson at that resolution. That solve ran on the CPU whatever the fit's device;
it now runs on the fit's. The re-mesh also keeps marching cubes' vertex sharing (``cleanup_mesh(weld=False)``):
merged by position, its 768^3 meshes came out open.
This script times both in one process on an open mesh (a sphere of radius 0.3 with a cap cut away, 327,680
faces before the cut) and prints the ratio, the peak GPU memory, and the Chamfer distance between the two meshes.
With ``--fallback`` it also re-meshes with the device's memory filled up to ``--leave-gib`` free, so that the
solve runs out of memory there and falls back to the CPU as a fit's does (many fits on one GPU), and prints
where it ran and the Chamfer distance to the device's mesh.

    PYTHONPATH=. python lab/final_remesh.py [--device cuda:0] [--resolutions 256 384 768]
        [--cpu-resolutions 256 384] [--fallback [--leave-gib 3]]

The CPU runs use every core this process may use (``torch.get_num_threads()``); resolutions left out of
``--cpu-resolutions`` are timed on the device only. The last line is the process's peak resident host memory
(``--device cpu --resolutions 768 --cpu-resolutions``: what a CPU re-mesh at 768^3, or a fit's fallback to it, needs).
"""
import argparse
import resource
import time
import warnings

import numpy as np
import torch
import trimesh

from wtopo.fitting import FitConfig
from wtopo.fitting._final_mesh import poisson_remesh
from wtopo.metrics import chamfer


def open_sphere() -> trimesh.Trimesh:
    s = trimesh.creation.icosphere(subdivisions=7, radius=0.3)
    s.apply_translation([0.5, 0.5, 0.5])
    return trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] < 0.7], process=True)


def run(mesh: trimesh.Trimesh, resolution: int, device: str,
        events: dict | None = None) -> tuple[trimesh.Trimesh, float, float]:
    """(mesh, seconds, peak GPU GiB) of one re-mesh; a first call on a device warms its kernels up.
    ``events``: filled with what the re-mesh recorded (``device``: where it ran)."""
    cfg = FitConfig()
    cfg.final.resolution = resolution
    if device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    sink = events if events is not None else {}  # an empty dict is the caller's: fill that one
    out = poisson_remesh(mesh, cfg, record=lambda _name, **k: sink.update(k), device=device)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated() / 2**30 if device.startswith("cuda") else 0.0
    return out, time.perf_counter() - t, peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--resolutions", type=int, nargs="+", default=[256, 384, 768])
    ap.add_argument("--cpu-resolutions", type=int, nargs="*", default=[256, 384])
    ap.add_argument("--fallback", action="store_true",
                    help="also re-mesh with the device's memory filled, to measure the CPU fallback")
    ap.add_argument("--leave-gib", type=float, default=3.0, help="device memory left free for --fallback")
    args = ap.parse_args()
    mesh = open_sphere()
    print(f"open sphere: {len(mesh.faces)} faces, watertight {mesh.is_watertight}; CPU threads "
          f"{torch.get_num_threads()}; device {args.device}")
    run(mesh, 64, args.device)  # warm-up (kernel compilation / loading)
    run(mesh, 64, "cpu")
    for r in args.resolutions:
        dev_mesh, t_dev, peak = run(mesh, r, args.device)
        line = f"{r}^3: {args.device} {t_dev:.2f} s (peak {peak:.2f} GiB, {len(dev_mesh.faces)} faces, " \
               f"watertight {dev_mesh.is_watertight})"
        if r in args.cpu_resolutions:
            cpu_mesh, t_cpu, _ = run(mesh, r, "cpu")
            c = chamfer(dev_mesh, cpu_mesh)
            line += f"; cpu {t_cpu:.2f} s: {t_cpu / t_dev:.1f}x; Chamfer between the two {c.chamfer:.2e} " \
                    f"(voxel {1.1 * 0.6 / r:.2e})"
        print(line, flush=True)
        if args.fallback and args.device.startswith("cuda"):
            # the caching allocator's blocks from the runs above are not free to the driver but are to the
            # re-mesh: hand them back first, or the re-mesh reuses them and never runs out
            torch.cuda.empty_cache()
            free, _ = torch.cuda.mem_get_info(args.device)
            hog = torch.empty(max(int(free - args.leave_gib * 2**30), 0), dtype=torch.uint8, device=args.device)
            events: dict = {}
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # the fallback's own warning, expected
                fb_mesh, t_fb, _ = run(mesh, r, args.device, events)
            del hog
            torch.cuda.empty_cache()
            c = chamfer(dev_mesh, fb_mesh)
            print(f"  with {args.leave_gib:g} GiB free: ran on {events.get('device')}, {t_fb:.2f} s, "
                  f"{len(fb_mesh.faces)} faces; Chamfer to the device's mesh {c.chamfer:.2e}", flush=True)
    r = np.linalg.norm(dev_mesh.vertices - 0.5, axis=1)
    print(f"last device mesh: radius {r.min():.4f}-{r.max():.4f} (truth 0.3 below the cut)")
    # the CPU solve's host memory decides whether a fallback survives on a small machine
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux
    print(f"host peak resident memory of this process: {peak_gb:.2f} GB")


if __name__ == "__main__":
    main()
