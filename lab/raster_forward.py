# SPDX-License-Identifier: Apache-2.0
"""#60 goal 2, forward alone: the public rasterize_surfels against gsplat's rasterization_2dgs at 100k and 1M
surfels, 800 px (bench_rasterize_gpu.py's scene), with other tile sizes and prefetch batches, the two-kernel
preparation and inputs copied in, and the kernel table of each forward alone. ``--rounds R`` then times gsplat
and our default forward alternately R times (each round 30 calls of each, the order swapped every round) and
prints the median ratio: one process's figure for the ratio, free of which runs first. Lab tool (nothing imports
it): python lab/raster_forward.py [--sizes ...]."""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks"))

import torch  # noqa: E402
from bench_rasterize_gpu import gsplat_inputs, make_camera, make_gsplat, make_surfels  # noqa: E402
from gpu_timing import profile_kernels, time_latency, time_pipelined  # noqa: E402

from wtopo import rasterize as R  # noqa: E402
from wtopo.rasterize import _replay  # noqa: E402
from wtopo.rasterize import _run as K  # noqa: E402

_last: list = [None]


def variant(params, cam, tile: int, batch: int, fused: bool = True, copies: bool = False):
    """Our no-grad forward with that tile size and prefetch batch; ``fused``: the one-kernel preparation of a
    render nothing differentiates (``_run.FUSED_FORWARD``); ``copies``: calls alternate between two copies of the
    surfels, so the replay copies its inputs in (the capture of calls whose tensors move) where it otherwise reads
    them in place. Captures are dropped whenever another variant is timed (the prefetch batch and the preparation
    are not part of a capture's shape)."""
    cfg = R.RasterConfig(tile_size=tile)
    name = (tile, batch, fused, copies)
    sets = [params, [p.detach().clone() for p in params]] if copies else [params]
    calls = [0]

    def fwd():
        if _last[0] != name:
            _replay.reset()
            _last[0] = name
        saved = K.PREFETCH_BATCH, K.FUSED_FORWARD
        K.PREFETCH_BATCH, K.FUSED_FORWARD = batch, fused
        try:
            with torch.no_grad():
                R.rasterize_surfels(*sets[calls[0] % len(sets)], cam, config=cfg)
            calls[0] += 1
        finally:
            K.PREFETCH_BATCH, K.FUSED_FORWARD = saved

    return fwd


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--res", type=int, default=800)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--rounds", type=int, default=0)
    args = ap.parse_args()
    cam = make_camera(args.res, args.res)
    for n in args.sizes:
        params = make_surfels(n, "cuda:0")
        ref = R.rasterize_surfels(*params, cam)
        leaves, viewmat, Km = gsplat_inputs(params, cam, ref.near)
        g = make_gsplat(cam, ref.near, ref.far)

        def gfwd(g=g, a=(leaves, viewmat, Km)):
            with torch.no_grad():
                g(*a)

        runs = {"gsplat": gfwd}
        for tile, batch in ((16, 32), (16, 16), (8, 16)):
            runs[f"tile {tile} batch {batch}"] = variant(params, cam, tile, batch)
        runs["two-kernel preparation"] = variant(params, cam, 8, 32, fused=False)
        runs["inputs copied in"] = variant(params, cam, 8, 32, copies=True)
        runs["tile 8 batch 32"] = variant(params, cam, 8, 32)  # the default, last: the rounds and profile reuse it
        base = None
        print(f"\nN = {n}, {args.res} px, forward alone (ms)")
        for name, fn in runs.items():
            lat = time_latency(fn, 5, 30)["ms"]
            pipe = time_pipelined(fn, 5, 30)["ms"]
            base = base or (lat, pipe)
            print(f"  {name:22s} {lat:7.3f} {pipe:7.3f}   {lat / base[0]:.2f}x {pipe / base[1]:.2f}x gsplat")
        if args.rounds:
            ours = runs["tile 8 batch 32"]
            ratios = []
            for r in range(args.rounds):
                order = [("gsplat", gfwd), ("ours", ours)][:: 1 if r % 2 else -1]
                got = {name: time_latency(fn, 3, 30)["ms"] for name, fn in order}
                ratios.append(got["ours"] / got["gsplat"])
            ratios.sort()
            print(f"  alternating, {args.rounds} rounds: ours / gsplat median {ratios[len(ratios) // 2]:.3f}x "
                  f"(min {ratios[0]:.3f}, max {ratios[-1]:.3f})")
        if args.profile:
            profile_kernels(runs["tile 8 batch 32"], f"wtopo forward, N={n}", top=14)
            profile_kernels(gfwd, f"gsplat forward, N={n}", top=10)
        del params, ref, leaves, runs, gfwd
        torch.cuda.empty_cache()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
