"""Lab (nothing imports it): the fit's plane sweep against the coarse-to-fine one (``lab/stereo_c2f.py``, as
``lab/run_c2f.py`` calls it) on an exchange folder's training views, as the fit runs it (its layout, every view on
a GPU): seconds (best of ``--repeats`` after a warm-up), confirmed points, and the share of training pixels no point
explains.

    python3 lab/c2f_time.py EXCH [--device cuda:0] [--repeats 2]
"""
import argparse
import json
import os
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

from exchange import load  # noqa: E402

import stereo_c2f  # noqa: E402
from wtopo.fitting.background import uncovered_pixels  # noqa: E402
from wtopo.fitting.scene_kind import analyse_layout  # noqa: E402
from wtopo.geometry import mvs  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("exchange")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    ex = load(a.exchange)
    scene = ex.scene().normalized()
    train = scene.split("train")
    layout = analyse_layout(train)
    dev = torch.device(a.device)
    images = torch.as_tensor(train.images).to(dev)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    runs = {"full": lambda: mvs.plane_sweep_points(train.cameras, images, layout.roi_lower, layout.roi_upper,
                                                     near=layout.near, device=dev),
            "c2f": lambda: stereo_c2f.c2f_points(train.cameras, images, layout.roi_lower, layout.roi_upper,
                                                 near=layout.near, device=dev, edges=True)}
    for name, fn in runs.items():
        best, out = float("inf"), None
        for _ in range(1 + a.repeats):
            sync()
            t = time.perf_counter()
            out = fn()
            sync()
            best = min(best, time.perf_counter() - t)
        unc = uncovered_pixels(train.cameras, out.points, device=dev)
        print(json.dumps({"exchange": os.path.basename(a.exchange.rstrip("/")), "sweep": name,
                          "views": len(train.cameras),
                          "size": [train.cameras[0].width, train.cameras[0].height], "s": round(best, 2),
                          "points": len(out.points),
                          "uncovered": round(float(sum(u.float().mean().item() for u in unc) / len(unc)), 4)}),
              flush=True)


if __name__ == "__main__":
    main()
