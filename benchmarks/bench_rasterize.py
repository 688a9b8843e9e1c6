# SPDX-License-Identifier: Apache-2.0
"""Benchmark rasterize_surfels (forward + backward) against the brute-force pure-torch reference.

Both run in the same process on the same random scene, in float32 (the reference is the test
oracle of ``tests/reference/rasterize.py``: every surfel at every pixel). The reference does not
fit in memory for a full image (it holds [pixels, surfels] tensors), so it is timed on two pixel
chunks and scaled to the image two ways: as a chunked reference would run (image / chunk times
the larger chunk's time) and by a linear fit ``t = a + b * pixels`` (per-surfel set-up ``a`` paid
once); the speed-up uses the smaller of the two.

The stage split is the rasterizer's own ``wtopo._profile.section`` self times (``rasterize_binning``,
``rasterize_sort``, ``rasterize_forward``, ``rasterize_backward``), collected around each run. They are
host wall times without device syncs: exact on CPU (Warp's CPU launches are synchronous); on CUDA a
stage is charged for the kernels it waits on, and the backward runs on autograd's device thread,
which sections do not collect.

Run: ``.venv/bin/python benchmarks/bench_rasterize.py [--sizes 10000 100000] [--res 256]``

``--bunny`` times instead the fit's own CPU case: the fit's entry (``wtopo.rasterize._rasterize_trusted``
with the fit's ``filter_sigma``, black background, SH degree 0) over the 32 views of the built-in bunny
(128 x 128) with about 12k surfels on the bunny's surface (or a saved fit's ``--surfels`` PLY), forward and
forward + backward (random upstream gradients on all six images), medians over the views and
``--repeats`` passes. ``--baseline DIR`` runs the same measurement on another tree of the package (for
instance ``git archive main | tar -x -C DIR``) in a child process, alternating with this one, and prints
the ratio.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections import defaultdict

import torch
from _from_tests import load  # beside this script

rasterize_reference = load("reference/rasterize.py").rasterize_reference

import wtopo  # noqa: E402
from wtopo import rasterize as R  # noqa: E402
from wtopo._profile import section  # noqa: E402
from wtopo.rasterize import _binning, _camera  # noqa: E402

IMAGES = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")
STAGES = ("binning", "sort", "forward", "backward")
"""Stages of the split: the rasterizer's sections ``rasterize_<stage>``."""


def scene(n: int, res: int, device: str = "cpu", seed: int = 0):
    """``n`` surfels filling a unit box 3 units in front of a ``res`` x ``res`` camera (SH degree 3)."""
    g = torch.Generator().manual_seed(seed)
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.7, width=res, height=res)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2.0
    quats = torch.randn(n, 4, generator=g)
    # surfel size ~ surface area per surfel of a few layers: radius 1.5-4 px at 10k, 0.5-1.3 px at 100k
    s = 0.06 * (10_000 / n) ** 0.5
    scales = torch.rand(n, 2, generator=g) * s + 0.5 * s
    ops = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, 16, 3, generator=g) * 0.3
    params = [t.to(device).requires_grad_(True) for t in (means, quats, scales, ops, sh)]
    return cam, params


def _loss(out: dict | R.RenderOutput, ups: dict):
    get = (lambda k: out[k]) if isinstance(out, dict) else (lambda k: getattr(out, k))
    return sum((get(k) * u).sum() for k, u in ups.items())


def _fit_path(*params, config=None):
    """The fit's unchecked entry (``wtopo.rasterize._rasterize_trusted``): no argument checks, black background."""
    cam = params[-1]
    bg = torch.zeros(3, dtype=params[0].dtype, device=params[0].device)
    return R._rasterize_trusted(*params[:-1], cam, sh_degree=None, background=bg,
                                config=config or R.RasterConfig())


def time_op(cam, params, repeats: int, config=None, op=None):
    """Median wall seconds of forward and backward, the last run's self seconds per section, and its output.

    ``op``: the entry timed, :func:`wtopo.rasterize.rasterize_surfels` (default) or :func:`_fit_path`.
    """
    op = op or R.rasterize_surfels
    g = torch.Generator().manual_seed(1)
    ups = {k: torch.randn((cam.height, cam.width, 3) if k in ("rgb", "normal") else (cam.height, cam.width),
                          generator=g) for k in IMAGES}
    fw, bw = [], []
    for _ in range(repeats + 1):  # the first run compiles / warms caches
        prof = defaultdict(float)
        with section("outside_rasterizer", add=lambda name, sec, prof=prof: prof.__setitem__(name, prof[name] + sec)):
            t0 = time.perf_counter()
            out = op(*params, cam, config=config)
            t1 = time.perf_counter()
            _loss(out, ups).backward()
            t2 = time.perf_counter()
        fw.append(t1 - t0)
        bw.append(t2 - t1)
        for p in params:
            p.grad = None
    return statistics.median(fw[1:]), statistics.median(bw[1:]), prof, out


def count_intersections(cam, params, config) -> int:
    """(tile, surfel) pairs the binning emits for this view (the rasterizer's private binning stage, run once)."""
    means, quats, scales, ops = (p.detach() for p in params[:4])
    near, far = _camera._default_clip(means, cam, None, None, config)
    _, tables = _camera._camera_tables(cam, means.device, means.dtype, config.tile_size)
    rec = _camera._camera_record(cam, _camera._clip_from_host(near, far, means.device).to(means.dtype), means.dtype,
                           config.filter_sigma)
    bins = _binning._bin(means, quats, scales, ops, rec, tables, cam, config, wtopo._bridge.warp_device(means.device))
    return int((bins.tile_end.numpy().astype("int64") - bins.tile_start.numpy()).sum())


def time_reference(cam, params, pixels: int, repeats: int = 1) -> float:
    """Wall seconds of the reference's forward + backward on the first ``pixels`` pixels of a tile-like patch."""
    h, w = cam.height, cam.width
    side = max(1, int(pixels**0.5))
    rows = torch.arange(side) + h // 2 - side // 2
    cols = torch.arange(pixels // side) + w // 2 - (pixels // side) // 2
    idx = (rows[:, None] * w + cols[None, :]).reshape(-1)
    g = torch.Generator().manual_seed(1)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        ref = rasterize_reference(*params, cam, near=0.15, far=300.0, pixels=idx)
        ups = {k: torch.randn(ref[k].shape, generator=g) for k in IMAGES}
        _loss(ref, ups).backward()
        times.append(time.perf_counter() - t0)
        for p in params:
            p.grad = None
    return min(times), int(idx.numel())


BUNNY_FILTER_SIGMA = 0.35  # the CPU plan's filter_sigma (wtopo.fitting.plan._FILTER_SIGMA["cpu"])


def bunny_state(n: int = 12_000, seed: int = 0, surfels: str | None = None):
    """The bunny's cameras and ``n`` surfels on its surface (or those of a surfel PLY), as float32 leaves.

    Like a fitted state: centres on the ground-truth surface, tangent to it, scales about the spacing,
    opacities spread over (0.05, 0.99) (a fit's have median 0.9 and a tail of faint ones), SH degree 0.
    """
    import numpy as np

    from wtopo import scenes

    sc = scenes.load("bunny")
    if surfels:
        from wtopo.io import read_surfels_ply

        a = read_surfels_ply(surfels)
        arrays = (a.means, a.quats, a.scales, a.opacities, a.sh)
    else:
        import trimesh
        from scipy.spatial import cKDTree

        from wtopo.fitting.surfels import normals_to_quats

        mesh = sc.gt_mesh
        pts, face = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
        rng = np.random.default_rng(seed)
        dist = cKDTree(pts).query(pts, k=4)[0][:, 1:].mean(1)
        quats = normals_to_quats(torch.as_tensor(mesh.face_normals[face], dtype=torch.float32)).numpy()
        scales = dist[:, None] * rng.uniform(0.5, 1.0, (len(pts), 2))
        opac = rng.uniform(0.05, 0.99, len(pts))
        sh = rng.normal(0.0, 0.5, (len(pts), 1, 3))
        arrays = (pts, quats, scales, opac, sh)
    params = [torch.tensor(np.asarray(x), dtype=torch.float32).requires_grad_(True) for x in arrays]
    return sc.cameras, params


def time_bunny(cams, params, repeats: int):
    """Median seconds of forward and of forward + backward per view (the fit's entry), and the split per view."""
    cfg = R.RasterConfig(filter_sigma=BUNNY_FILTER_SIGMA)
    bg = torch.zeros(3)
    g = torch.Generator().manual_seed(1)
    h, w = cams[0].height, cams[0].width
    ups = [torch.randn((h, w, 3) if k in ("rgb", "normal") else (h, w), generator=g) for k in IMAGES]
    for cam in cams:  # warm-up: compiles, per-camera tables
        R._rasterize_trusted(*params, cam, sh_degree=0, background=bg, config=cfg)
    fw, fb = [], []
    prof = defaultdict(float)
    for _ in range(repeats):
        for cam in cams:
            with section("outside_rasterizer", add=lambda name, sec: prof.__setitem__(name, prof[name] + sec)):
                t0 = time.perf_counter()
                out = R._rasterize_trusted(*params, cam, sh_degree=0, background=bg, config=cfg)
                t1 = time.perf_counter()
                torch.autograd.backward([getattr(out, k) for k in IMAGES], ups)
                t2 = time.perf_counter()
            fw.append(t1 - t0)
            fb.append(t2 - t0)
            for p in params:
                p.grad = None
    split = {k: v / len(fw) for k, v in prof.items()}
    return statistics.median(fw), statistics.median(fb), split


def _bunny_child(args) -> None:
    """One measurement, printed as JSON (the ``--baseline`` child and the alternating rounds)."""
    import json

    cams, params = bunny_state(args.bunny_n, surfels=args.surfels)
    fw, fb, split = time_bunny(cams, params, args.repeats)
    print(json.dumps({"forward": fw, "total": fb, "split": split, "n": int(params[0].shape[0]),
                      "package": wtopo.__file__}))


def main_bunny(args) -> None:
    """``--bunny``: this tree and, with ``--baseline``, another one, alternately in child processes."""
    import json
    import subprocess
    import sys

    trees = {"this": None}
    if args.baseline:
        trees = {"baseline": args.baseline, "this": None}
    results = {k: [] for k in trees}
    for _ in range(args.rounds):
        for name, root in trees.items():
            env = dict(os.environ)
            if root:
                env["PYTHONPATH"] = os.pathsep.join([root, env.get("PYTHONPATH", "")])
            cmd = [sys.executable, __file__, "--bunny-child", "--bunny-n", str(args.bunny_n), "--repeats",
                   str(args.repeats)] + (["--surfels", args.surfels] if args.surfels else [])
            r = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
                           .strip().splitlines()[-1])
            results[name].append(r)
            split = "  ".join(f"{k.removeprefix('rasterize_')} {v * 1e3:.1f}" for k, v in sorted(r["split"].items()))
            print(f"{name:8s} N={r['n']}  forward {r['forward'] * 1e3:6.1f} ms  forward+backward "
                  f"{r['total'] * 1e3:6.1f} ms   [{split}] ms  ({os.path.dirname(r['package'])})", flush=True)
    if args.baseline:
        med = {k: {q: statistics.median(r[q] for r in v) for q in ("forward", "total")} for k, v in results.items()}
        for q in ("forward", "total"):
            print(f"{q:8s} baseline {med['baseline'][q] * 1e3:6.1f} ms  this {med['this'][q] * 1e3:6.1f} ms  "
                  f"speed-up {med['baseline'][q] / med['this'][q]:.2f}x (medians of {args.rounds} rounds)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bunny", action="store_true", help="the CPU fit's case: bunny, 128 px, ~12k surfels")
    ap.add_argument("--bunny-n", type=int, default=12_000, help="surfels of --bunny (without --surfels)")
    ap.add_argument("--surfels", default=None, help="--bunny: a surfel PLY (e.g. a fit's surfels.ply)")
    ap.add_argument("--baseline", default=None, help="--bunny: a tree of the package to compare against")
    ap.add_argument("--rounds", type=int, default=3, help="--bunny: alternating rounds per tree")
    ap.add_argument("--bunny-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--tile", type=int, default=None, help="tile size (default: RasterConfig's)")
    ap.add_argument("--no-reference", action="store_true", help="time the op only")
    ap.add_argument("--fit-path", action="store_true",
                    help="also time the fit's unchecked entry (no argument checks) in the same process")
    args = ap.parse_args()
    if args.bunny_child:
        return _bunny_child(args)
    if args.bunny:
        return main_bunny(args)
    tile = R.RasterConfig().tile_size if args.tile is None else args.tile
    print(f"device {args.device}, threads {wtopo._bridge.cpu_threads()}, image {args.res}x{args.res}, float32, "
          f"tile {tile}, load average {os.getloadavg()[0]:.1f}")
    for n in args.sizes:
        cam, params = scene(n, args.res, args.device)
        cfg = R.RasterConfig() if args.tile is None else R.RasterConfig(tile_size=args.tile)
        fw, bw, prof, out = time_op(cam, params, args.repeats, cfg)
        px = args.res * args.res
        total = fw + bw
        split = {k: prof.get(f"rasterize_{k}", 0.0) for k in STAGES}
        cover = float((out.alpha > 0).float().mean())
        print(f"N={n}: intersections {count_intersections(cam, params, cfg)}, coverage {cover:.2f}, "
              f"visible {int((out.visibility > 0).sum())}")
        print(f"  op   forward {fw * 1e3:8.1f} ms  backward {bw * 1e3:8.1f} ms  total {total * 1e3:8.1f} ms  "
              f"{px / total / 1e6:6.3f} Mpixel/s")
        print("  split (last run) " + "  ".join(f"{k} {v * 1e3:.1f} ms" for k, v in split.items()))
        if args.fit_path:
            ffw, fbw, _, _ = time_op(cam, params, args.repeats, cfg, op=_fit_path)
            print(f"  fit path forward {ffw * 1e3:8.1f} ms  backward {fbw * 1e3:8.1f} ms  "
                  f"total {(ffw + fbw) * 1e3:8.1f} ms  "
                  f"(public / fit path: forward {fw / ffw:.2f}x, total {total / (ffw + fbw):.2f}x)")
        if args.no_reference:
            continue
        p1, p2 = (64, 256) if n <= 20_000 else (16, 64)  # memory: [pixels, n] tensors
        t1, q1 = time_reference(cam, params, p1)
        t2, q2 = time_reference(cam, params, p2)
        chunked = t2 * px / q2
        linear = t1 + max(0.0, (t2 - t1) / (q2 - q1)) * (px - q1)
        ref_full = min(chunked, linear)
        print(f"  reference  {q1} px: {t1:.2f} s, {q2} px: {t2:.2f} s -> {px} px: chunked {chunked:.1f} s, "
              f"linear fit {linear:.1f} s ({px / ref_full:.0f} pixel/s)")
        print(f"  speed-up vs reference: {ref_full / total:.0f}x")


if __name__ == "__main__":
    main()
