# SPDX-License-Identifier: Apache-2.0
"""Plane-sweep stereo (:func:`wtopo.geometry.mvs.plane_sweep_points`, a fit's initial surfels) against another
version of its module, in one process.

The capture is DTU scan24 from ``../shared/data`` (research data, read in place; a synthetic bunny of 32 views at
256 px where it is absent), in the fit's normalised frame, its first ``--views`` views, downscaled ``--scale`` times,
swept over the normalised frame's unit box. Each version runs ``--repeats`` times (best kept, after one warm-up
run on CUDA); the table gives seconds, the confirmed points and the ratio to the package's module.

``--against FILE`` is another version of ``wtopo/geometry/mvs.py`` (e.g. ``git show REV:wtopo/geometry/mvs.py >
/tmp/mvs_rev.py``), loaded as a sibling module so its relative imports resolve.

Commands (the figures go to benchmarks/gpu.md by hand)::

    .venv/bin/python benchmarks/bench_mvs.py --views 8 --scale 2 --against /tmp/mvs_rev.py        # CPU
    python benchmarks/bench_mvs.py --device cuda --views 42 --against /tmp/mvs_rev.py               # DTU's sweep
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch
from _from_tests import load_file  # beside this script

from wtopo.geometry import mvs

DTU = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "dtu_scan24")


def _scene(views: int, scale: float, data: str = DTU):
    from wtopo import load_scene, scenes

    scene = load_scene(data) if os.path.isdir(data) else scenes.load("bunny", n_views=32, resolution=256)
    scene = scene.normalized()
    if scale > 1:
        scene = scene.downscaled(scale)
    return scene.cameras[:views], scene.images[:views]


def _time(mod, cams, images, device: str, repeats: int) -> tuple[float, int]:
    lo, hi = -np.ones(3), np.ones(3)

    def run():
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        r = mod.plane_sweep_points(cams, images, lo, hi, near=0.05, device=device)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        return time.perf_counter() - t, len(r.points)

    if device.startswith("cuda"):
        run()  # the first CUDA run pays for its kernels' loading
    best = min(run() for _ in range(repeats))
    return best


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--scale", type=float, default=1.0, help="downscale the images this many times")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--data", default=DTU, help="the capture (default: DTU scan24 in ../shared/data)")
    ap.add_argument("--against", default=None, help="another version of wtopo/geometry/mvs.py, timed beside it")
    a = ap.parse_args(argv)
    cams, images = _scene(a.views, a.scale, a.data)
    print(f"{len(cams)} views of {cams[0].width} x {cams[0].height}, device {a.device}", flush=True)
    rows = [("wtopo.geometry.mvs", *_time(mvs, cams, images, a.device, a.repeats))]
    if a.against:
        other = load_file(a.against, "wtopo.geometry._mvs_against")
        rows.append((os.path.basename(a.against), *_time(other, cams, images, a.device, a.repeats)))
    print(f"{'module':<28} {'s':>8} {'points':>9} {'ratio':>7}")
    for name, s, n in rows:
        print(f"{name:<28} {s:8.2f} {n:9d} {s / rows[0][1]:7.2f}")


if __name__ == "__main__":
    main()
