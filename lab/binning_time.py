# SPDX-License-Identifier: Apache-2.0
"""The rasterizer's binning and sort sections for one call of ``bench_rasterize_gpu.py``'s scene (N random surfels,
800 x 800 px, tile 8), best of three calls after a warm-up: ``rasterize_binning`` and ``rasterize_sort`` self times.

    cd benchmarks && ../.venv/bin/python ../lab/binning_time.py 1000000 [--device cuda:0]

Another tree of the package: ``PYTHONPATH=DIR`` with ``DIR/wtopo/kernels`` a link to ``DIR/kernels``.
"""

import argparse
import os
import sys

import torch

sys.path.insert(0, os.getcwd())
import bench_rasterize_gpu as B  # noqa: E402

import wtopo.rasterize as R  # noqa: E402
from wtopo._profile import section  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("n", type=int)
ap.add_argument("--device", default="cpu")
a = ap.parse_args()
cam = B.make_camera(800, 800)
real = R._bin
best: dict = {}


def timed(*args, **kw):
    times: dict = {}

    def add(name, s):
        times[name] = times.get(name, 0.0) + s

    sync = torch.cuda.synchronize if a.device.startswith("cuda") else None
    for rep in range(4):
        times.clear()
        with section("bin", add=add, sync=sync):
            bins = real(*args, **kw)
        if rep:
            for k, v in times.items():
                best[k] = min(v, best.get(k, v))
    return bins


R._bin = timed
params = B.make_surfels(a.n, a.device)
with torch.no_grad():
    R.rasterize_surfels(*[p.detach() for p in params], cam)
print(a.n, {k: round(v * 1e3, 2) for k, v in best.items() if k != "bin"}, "ms")
