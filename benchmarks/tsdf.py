# SPDX-License-Identifier: Apache-2.0
"""Benchmark the Warp TSDF fusion against Open3D's ScalableTSDFVolume, in one process.

The fit's two fusions at the fit's sizes: 48 views of the Stanford bunny (exact z-depth from the
mesh ray caster, one colour per view) at 160x120 (the CPU default's images) and 800x600 (a GPU
capture), fused at 192^3 and 384^3 voxels over the bunny's box (+5 %), truncation 4 voxels, each
view cut at the box's farthest corner: exactly what ``wtopo.fitting.tsdf.fuse_depths`` does in a fit.
The fit's fusion is timed through ``fuse_depths``, Open3D through the tests' reference of the same
contract (``tests/reference/tsdf_open3d.py``): host preparation, fusion, mesh extraction, ``trimesh``
construction and the crop to the box, median of ``--repeats`` after one warm-up run
(Warp's kernel compilation is not timed). Printed per case: seconds of each, the ratio Warp /
Open3D (below 1: Warp is faster), faces, the Chamfer distance between the two meshes in voxels,
Warp's time split (block test, integration, marching cubes) and, on CUDA, Warp's peak memory pool.

Run (CPU, 2 cores, Open3D on the CPU too)::

    .venv/bin/python benchmarks/tsdf.py

on a GPU (Open3D stays on the CPU; ``--no-open3d`` where it is not installed)::

    .venv/bin/python benchmarks/tsdf.py --device cuda:0 --grids 192 384 768
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict

import numpy as np
import torch
from _from_tests import load

import wtopo  # noqa: F401  (configures Warp)
from wtopo._profile import section
from wtopo.fitting.tsdf import FusionBounds, fuse_depths
from wtopo.metrics import chamfer
from wtopo.ops import raycast_mesh
from wtopo.scenes import bunny_mesh, rig_cameras

_MARGIN = 0.05  # the box grows by this fraction of its longest side on every side (as auto_bounds)
_TRUNCATION_VOXELS = 4.0  # tsdf.truncation_voxels' default

fuse_depths_open3d = load("reference/tsdf_open3d.py").fuse_depths_open3d  # the tests' Open3D reference


def make_views(n_views: int, size: tuple[int, int], device: str):
    """Cameras around the unit-sized bunny, their exact z-depth (NumPy) and a colour per view."""
    mesh, _ = bunny_mesh()
    v = np.asarray(mesh.vertices, np.float64)
    v = (v - v.mean(0)) / np.ptp(v, axis=0).max()
    center, radius = np.zeros(3), 0.5 * float(np.linalg.norm(np.ptp(v, axis=0)))
    cams = rig_cameras("sphere", n_views, center, radius, resolution=size, fov=0.7)
    verts = torch.as_tensor(v, dtype=torch.float32, device=device)
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int32, device=device)
    depths = [raycast_mesh(verts, faces, c).depth.cpu().numpy() for c in cams]
    rng = np.random.default_rng(0)
    colors = [np.broadcast_to(rng.random(3).astype(np.float32), d.shape + (3,)).copy() for d in depths]
    return v, cams, depths, colors


def bounds_for(v: np.ndarray, grid: int) -> FusionBounds:
    lo, hi = v.min(0), v.max(0)
    side = float(np.max(hi - lo))
    lo, hi = lo - _MARGIN * side, hi + _MARGIN * side
    voxel = float(np.max(hi - lo)) / grid
    return FusionBounds(lo, hi, voxel, _TRUNCATION_VOXELS * voxel)


def timed(fn, repeats: int, device: str):
    """Median wall seconds of ``fn()`` over ``repeats`` runs, its last result and its last section times."""
    times, out, prof = [], None, {}
    for _ in range(repeats):
        p = defaultdict(float)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        with section("fuse", add=lambda name, sec, p=p: p.__setitem__(name, p[name] + sec)):
            out = fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
        prof = p
    return statistics.median(times), out, prof


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", help="where the Warp fusion runs: cpu or cuda:N")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--sizes", nargs="+", default=["160x120", "800x600"], help="image sizes WxH")
    ap.add_argument("--grids", type=int, nargs="+", default=[192, 384], help="voxels along the box's longest side")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-open3d", action="store_true", help="time the Warp fusion alone")
    args = ap.parse_args()
    import warp as wp

    cuda = args.device.startswith("cuda")
    print(f"TSDF fusion, {args.views} views, Warp on {args.device}, Open3D on the CPU; median of {args.repeats}")
    head = (f"{'images':>9} {'grid':>5} {'warp s':>8} {'open3d s':>9} {'warp/o3d':>9} {'faces warp':>11} "
            f"{'faces o3d':>10} {'chamfer vox':>12}  warp split (blocks / integrate / marching cubes s)")
    print(head)
    for size in args.sizes:
        w, h = (int(x) for x in size.split("x"))
        v, cams, depths, colors = make_views(args.views, (w, h), args.device)
        for grid in args.grids:
            b = bounds_for(v, grid)
            views = (cams, depths, colors)
            warp = lambda b=b, views=views: fuse_depths(*views, b, device=args.device)  # noqa: E731
            warp()  # compile the kernels, fill the memory pool
            if cuda:
                wdev = wp.get_device(args.device)
                base = wp.get_mempool_used_mem_current(wdev)
            tw, mw, prof = timed(warp, args.repeats, args.device)
            split = " / ".join(f"{prof.get(k, 0.0):.2f}" for k in ("tsdf_blocks", "tsdf_integrate", "marching_cubes"))
            mem = ""
            if cuda:
                mem = f", Warp pool peak {(wp.get_mempool_used_mem_high(wdev) - base) / 2**20:.0f} MiB"
            if args.no_open3d:
                print(f"{size:>9} {grid:>5} {tw:8.2f} {'-':>9} {'-':>9} {len(mw.faces):>11} {'-':>10} {'-':>12}  "
                      f"{split}{mem}")
                continue
            o3d = lambda b=b, views=views: fuse_depths_open3d(*views, b)  # noqa: E731
            to, mo, _ = timed(o3d, args.repeats, "cpu")
            ch = chamfer(mw, mo, n_samples=100_000).chamfer / b.voxel
            print(f"{size:>9} {grid:>5} {tw:8.2f} {to:9.2f} {tw / to:9.2f} {len(mw.faces):>11} {len(mo.faces):>10} "
                  f"{ch:12.3f}  {split}{mem}", flush=True)


if __name__ == "__main__":
    main()
