"""Lab (nothing imports it): the package's density control against lab/coevo_densify.py's patch (clone/split by
gradient in the first half of the co-evolution), one CPU fit per scene and variant, in sequence: held-out PSNR,
Chamfer and F-score, surfel count, time.

    PYTHONPATH=. .venv/bin/python lab/coevo_ab.py bunny [--seed 0] [--variants default coevo]
"""
import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", nargs="+", default=["default", "coevo"])
    a = ap.parse_args()

    import wtopo
    import wtopo.fitting._strategy as st
    from wtopo import scenes
    from wtopo.fitting.config import FitConfig

    base = st.DensityStrategy.step_post_backward, st.DensityStrategy.step_end
    import coevo_densify as patch

    for name in a.scenes:
        for v in a.variants:
            st.DensityStrategy.step_post_backward, st.DensityStrategy.step_end = (
                base if v == "default" else (patch.step_post_backward, patch.step_end))
            scene = scenes.load(name)
            cfg = FitConfig()
            cfg.runtime.device = "cpu"
            cfg.runtime.usd_every = 0
            cfg.runtime.seed = a.seed
            res = wtopo.fit(scene, cfg, progress=False)
            rep = res.report
            row = {"scene": name, "variant": v, "seed": a.seed, "psnr": rep.get("psnr"), "surfels": rep.get("surfels"),
                   "elapsed_s": rep.get("elapsed_s"), "faces": rep["mesh"]["faces"]}
            if rep.get("chamfer") is not None:
                row.update(chamfer_pct=100 * rep["chamfer"], f_score=rep.get("f_score"))
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
