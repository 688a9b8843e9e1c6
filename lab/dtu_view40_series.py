"""Lab (nothing imports it): when DTU scan24's held-out view 40 goes wrong in a fit. One CPU fit at the default on
the peers' split (every 8th view held out), the held-out PSNR of every view at each of the fit's evaluations
(``runtime.eval_every``) and of the surfels at the start of each stage, printed as a table per iteration.

    PYTHONPATH=. .venv/bin/python lab/dtu_view40_series.py [--data ../shared/data/dtu_scan24] [--set KEY=VALUE]
"""
import argparse
import json
import os
import sys

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from dtu_view40 import peers_split  # noqa: E402  (beside this script)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=os.path.join(HERE, "..", "..", "shared", "data", "dtu_scan24"))
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--eval-every", type=int, default=100)
    a = ap.parse_args()

    import wtopo
    from wtopo import metrics
    from wtopo.cli import _apply_set
    from wtopo.fitting import evaluate, loop
    from wtopo.fitting.config import FitConfig

    rows = []
    current = {"it": 0}
    orig_step = loop.FitRun._step

    def step(self, stage):
        current["it"] = self.it
        return orig_step(self, stage)

    loop.FitRun._step = step
    orig = evaluate.Evaluator.image_metrics

    def image_metrics(self, surfels):
        out = orig(self, surfels)
        per = []
        with torch.no_grad():
            for cam, img in zip(self.test.cameras, self.test.images):
                rgb = self.render(surfels, cam).rgb.clamp(0, 1)
                per.append(round(float(metrics.psnr(rgb, img.to(rgb.device))), 2))
        rows.append({"it": current["it"] + 1, "surfels": len(surfels), "psnr": per})
        print(json.dumps(rows[-1]), flush=True)
        return out

    evaluate.Evaluator.image_metrics = image_metrics
    scene, test = peers_split(a.data)
    cfg = FitConfig()
    for item in ["runtime.device=cpu", "runtime.usd_every=0", f"runtime.eval_every={a.eval_every}", *a.set]:
        _apply_set(cfg, item)
    res = wtopo.fit(scene, cfg, progress=False)
    print("views", test)
    print("final", json.dumps({"psnr": res.report.get("psnr"), "events": [e for e in res.report.get("events", [])
                                                                          if e.get("kind") != "densify"][:40]}))
    arr = np.array([r["psnr"] for r in rows])
    print("view 40 series:", [(r["it"], r["psnr"][test.index(40)]) for r in rows])
    print("mean series:", [(r["it"], round(float(np.mean(r["psnr"])), 2)) for r in rows], arr.shape)


if __name__ == "__main__":
    main()
