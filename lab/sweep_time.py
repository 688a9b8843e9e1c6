"""Lab (nothing imports it): the fit's plane sweep on an exchange folder's training views as a fit runs it (its
layout; a CPU fit's 24 views, every view on CUDA): seconds (best of ``--repeats`` after a warm-up), confirmed
points and the share of training pixels no point explains. ``--save`` keeps the points
(npz) to compare two commits.

    python3 lab/sweep_time.py EXCH [--device cpu] [--repeats 1] [--save out.npz]
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

from exchange import load  # noqa: E402

from wtopo.fitting._init_surfels import _CPU_STEREO_VIEWS  # noqa: E402
from wtopo.fitting.background import uncovered_pixels  # noqa: E402
from wtopo.fitting.scene_kind import analyse_layout  # noqa: E402
from wtopo.geometry import mvs  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("exchange")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--save", default=None)
    a = ap.parse_args()
    scene = load(a.exchange).scene().normalized()
    train = scene.split("train")
    layout = analyse_layout(train)
    dev = torch.device(a.device)
    images = torch.as_tensor(train.images).to(dev)
    max_views = None if dev.type == "cuda" else _CPU_STEREO_VIEWS

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    best, out = float("inf"), None
    for _ in range(1 + a.repeats):
        sync()
        t = time.perf_counter()
        out = mvs.plane_sweep_points(train.cameras, images, layout.roi_lower, layout.roi_upper, near=layout.near,
                                     device=dev, max_views=max_views)
        sync()
        best = min(best, time.perf_counter() - t)
    unc = uncovered_pixels(train.cameras, out.points, device=dev)
    if a.save:
        np.savez(a.save, points=out.points, normals=out.normals, colors=out.colors)
    print(json.dumps({"exchange": os.path.basename(a.exchange.rstrip("/")), "device": str(dev),
                      "views": min(len(train.cameras), max_views or 10**9),
                      "size": [train.cameras[0].width, train.cameras[0].height], "s": round(best, 2),
                      "points": len(out.points),
                      "uncovered": round(float(sum(u.float().mean().item() for u in unc) / len(unc)), 4)}),
          flush=True)


if __name__ == "__main__":
    main()
