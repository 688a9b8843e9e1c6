# SPDX-License-Identifier: Apache-2.0
"""One proxy-mesh step, stage by stage, on CPU or CUDA: time and peak memory.

The step the fit runs every co-evolution iteration: oriented points (5 per surfel) -> Poisson
(trilinear scatter + FFT solve) -> marching cubes -> BVH build -> ray cast of one view -> a
loss on mesh depth and normal -> backward through all of it into the surfel parameters.
Surfels are placed on the bunny surface (one per sampled point, tangent to it), so the mesh has
the size a real fit sees.

Also times the surfel rasterizer forward + backward at the same view size with ``--surfels``.

Command (GPU figures in benchmarks/README.md)::

    python benchmarks/bench_proxy_chain.py --device cuda:0 --resolution 256 --view 800 --surfels 100000 1000000
    python benchmarks/bench_proxy_chain.py --device cpu --resolution 128 --view 256 --surfels 10000
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
import trimesh
import warp as wp

import wtopo
from wtopo import ops, scenes


def _sync(device):
    if str(device).startswith("cuda"):
        torch.cuda.synchronize(device)
        wp.synchronize_device(str(device))


def _quat_from_normals(n: np.ndarray) -> np.ndarray:
    """w-first quaternions rotating +z onto each unit normal."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(np.broadcast_to(z, n.shape), n)
    w = 1.0 + n[:, 2]
    q = np.concatenate([w[:, None], axis], axis=1)
    flip = w < 1e-6  # normal == -z: rotate pi about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def bunny_surfels(n: int, device, seed: int = 0):
    """Surfels tangent to the bunny, in the unit cube; returns tensors and the camera."""
    mesh, _ = scenes.bunny_mesh()
    v = np.asarray(mesh.vertices)
    lo, hi = v.min(0), v.max(0)
    s = 0.8 / (hi - lo).max()
    unit = trimesh.Trimesh((v - 0.5 * (lo + hi)) * s + 0.5, mesh.faces, process=False)
    pts, fid = trimesh.sample.sample_surface(unit, n, seed=seed)
    nrm = np.asarray(unit.face_normals)[fid]
    spacing = np.sqrt(unit.area / n)
    t = lambda a: torch.tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    means = t(pts).requires_grad_(True)
    quats = t(_quat_from_normals(nrm)).requires_grad_(True)
    scales = t(np.full((n, 2), 0.7 * spacing)).requires_grad_(True)
    opac = t(np.full(n, 0.9)).requires_grad_(True)
    colors = t(np.random.default_rng(seed).random((n, 3))).requires_grad_(True)
    return means, quats, scales, opac, colors


def chain_step(params, camera, resolution, raycaster, device, times):
    means, quats, scales, opac, _ = params

    def mark(name, t0):
        _sync(device)
        t1 = time.perf_counter()
        times[name] = times.get(name, 0.0) + (t1 - t0)
        return t1

    t = time.perf_counter()
    op = ops.oriented_points(means, quats, scales, opac, samples=5)
    t = mark("oriented_points", t)
    field = ops.poisson_indicator(op.points, op.normals, op.weights, resolution, sigma=1.0, padding=0.1)
    t = mark("scatter+poisson", t)
    verts, faces = ops.marching_cubes(field.chi, 0.0, lower=field.lower, upper=field.upper)
    t = mark("marching_cubes", t)
    raycaster.update(verts.detach(), faces)
    t = mark("bvh_build", t)
    render = raycaster.raycast(verts, faces, camera)
    t = mark("raycast", t)
    m = render.mask
    loss = (render.depth[m] - 1.0).abs().mean() + (1 - render.normal[m][:, 2]).mean()
    loss.backward()
    t = mark("backward", t)
    return int(faces.shape[0]), int(m.sum())


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--view", type=int, default=256, help="image width = height of the ray-cast view")
    p.add_argument("--points", type=int, default=100_000, help="surfels feeding the proxy mesh")
    p.add_argument("--surfels", type=int, nargs="*", default=[], help="rasterizer sizes to time")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    dev = args.device
    cuda = dev.startswith("cuda")
    camera = wtopo.Camera.look_at((0.5, 0.5, -1.2), (0.5, 0.5, 0.5), (0, -1, 0), fov_x=0.9,
                                  width=args.view, height=args.view)
    result = {"device": torch.cuda.get_device_name(dev) if cuda else "cpu", "resolution": args.resolution,
              "view": args.view, "points": args.points}
    params = bunny_surfels(args.points, dev)
    from wtopo.raycast import MeshRaycaster

    raycaster = MeshRaycaster()
    chain_step(params, camera, args.resolution, raycaster, dev, {})  # compile / warm up
    if cuda:
        torch.cuda.reset_peak_memory_stats(dev)
        free0 = torch.cuda.mem_get_info(dev)[0]
    times = {}
    for _ in range(args.repeats):
        for q in params:
            q.grad = None
        faces, hits = chain_step(params, camera, args.resolution, raycaster, dev, times)
    times = {k: 1000 * v / args.repeats for k, v in times.items()}
    result["chain_ms"] = times
    result["chain_total_ms"] = sum(times.values())
    result["faces"], result["pixels_hit"] = faces, hits
    if cuda:
        result["torch_peak_MB"] = torch.cuda.max_memory_allocated(dev) / 2**20
        result["warp_mempool_high_MB"] = wp.get_mempool_used_mem_high(dev) / 2**20
        result["device_used_delta_MB"] = (free0 - torch.cuda.mem_get_info(dev)[0]) / 2**20
    print(json.dumps(result, indent=2))

    raster = []
    for n in args.surfels:
        means, quats, scales, opac, colors = bunny_surfels(n, dev, seed=1)

        def once(means=means, quats=quats, scales=scales, opac=opac, colors=colors):
            out = ops.rasterize_surfels(means, quats, scales, opac, colors, camera)
            loss = out.rgb.mean() + out.depth.mean() + out.normal.mean()
            loss.backward()
            return out

        once()
        _sync(dev)
        if cuda:
            torch.cuda.reset_peak_memory_stats(dev)
        tf = tb = 0.0
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = ops.rasterize_surfels(means, quats, scales, opac, colors, camera)
            loss = out.rgb.mean() + out.depth.mean() + out.normal.mean()
            _sync(dev)
            t1 = time.perf_counter()
            loss.backward()
            _sync(dev)
            t2 = time.perf_counter()
            tf += t1 - t0
            tb += t2 - t1
        row = {"surfels": n, "forward_ms": 1000 * tf / args.repeats, "backward_ms": 1000 * tb / args.repeats,
               "pixels_covered": int((out.alpha > 0).sum())}
        if cuda:
            row["torch_peak_MB"] = torch.cuda.max_memory_allocated(dev) / 2**20
            row["warp_mempool_high_MB"] = wp.get_mempool_used_mem_high(dev) / 2**20
        raster.append(row)
        print(json.dumps(row))
    result["rasterizer"] = raster
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
