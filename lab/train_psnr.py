"""Lab (nothing imports it): PSNR of every view of an exported exchange folder (training and held-out), rendered from
a run's ``surfels.ply`` (the caller's frame) with the fit's screen-space filter (``plan.json``), whole image.

DTU's held-out view 40 loses 4-10 dB in some fits: when its training neighbours (38, 39, 41) are as badly fitted, the
fit did not converge there (an optimisation problem); when they are fitted well, view 40 is a generalisation gap.

    python lab/train_psnr.py EXCH RUN [RUN ...]      # RUN: a run_wtopo.py result folder or its run/ folder
"""
import argparse
import json
import os
import sys

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))
from exchange import load  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("exchange")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    a = ap.parse_args()
    from wtopo import ops
    from wtopo.io import read_surfels_ply

    ex = load(a.exchange)
    scene = ex.scene()
    test = set(ex.test)
    for run in a.runs:
        d = os.path.join(run, "run") if os.path.isdir(os.path.join(run, "run")) else run
        s = read_surfels_ply(os.path.join(d, "surfels.ply"))
        with open(os.path.join(d, "plan.json")) as f:
            sigma = json.load(f)["filter_sigma"]["value"]
        t = [torch.as_tensor(x, device=a.device) for x in (s.means, s.quats, s.scales, s.opacities, s.sh)]
        degree = int(round(np.sqrt(s.sh.shape[1]))) - 1
        psnr = {}
        for i, cam in enumerate(scene.cameras):
            with torch.no_grad():
                r = ops.rasterize_surfels(*t, cam, sh_degree=degree, config=ops.RasterConfig(filter_sigma=sigma))
            photo = scene.images[i].to(a.device)
            psnr[i] = float(-10 * torch.log10(((r.rgb.clamp(0, 1) - photo) ** 2).mean()))
        train = {i: p for i, p in psnr.items() if i not in test}
        worst = sorted(train, key=train.get)[:6]
        print(f"{run}: training mean {np.mean(list(train.values())):.2f} dB, worst "
              f"{', '.join(f'{i}: {train[i]:.2f}' for i in worst)}; held-out "
              f"{', '.join(f'{i}: {psnr[i]:.2f}' for i in sorted(test))}; views 37-41 "
              f"{', '.join(f'{i}: {psnr[i]:.2f}' for i in range(37, 42) if i in psnr)}")


if __name__ == "__main__":
    main()
