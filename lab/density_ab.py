"""A/B of the warm-up's density-control constants on one scene (a lab script: nothing imports it).

    python lab/density_ab.py SCENE OUT VARIANT [--device cuda:0] [--set KEY=VALUE ...]

VARIANT: base (the shipped constants) or 3dgs (3DGS/2DGS's gradient threshold 2e-4 and prune opacity 0.005).
Prints one JSON line: variant, wall, surfels, held-out PSNR/SSIM, Chamfer/F where the scene has them."""
import json
import sys
import time

import wtopo
from wtopo.cli import _apply_set
from wtopo.fitting import _strategy, densify
from wtopo.fitting.config import FitConfig

VARIANTS = {"base": {}, "3dgs": {"grad": 2e-4, "prune": 0.005}, "grad2": {"grad": 2e-4}}


def main():
    scene, out, variant, *rest = sys.argv[1:]
    v = VARIANTS[variant]
    if "grad" in v:
        densify.GRAD_THRESHOLD = v["grad"]
    if "prune" in v:
        _strategy.PRUNE_OPACITY = v["prune"]
    sets = [rest[i + 1] for i in range(len(rest)) if rest[i] == "--set"]
    device = next((rest[i + 1] for i in range(len(rest)) if rest[i] == "--device"), "cpu")
    cfg = FitConfig()
    for item in sets:
        _apply_set(cfg, item)
    cfg.runtime.device = device
    t = time.perf_counter()
    from wtopo.loaders import load_scene

    res = wtopo.fit(load_scene(scene), cfg, out_dir=out, progress=False)
    wall = time.perf_counter() - t
    with open(f"{out}/report.json") as fh:
        rep = json.load(fh)
    print(json.dumps({"variant": variant, "scene": scene, "wall_s": round(wall, 1),
                      "surfels": len(res.surfels) if hasattr(res, "surfels") else None,
                      **{k: rep.get(k) for k in ("psnr", "ssim", "psnr_on", "chamfer", "f_score")}}))


if __name__ == "__main__":
    main()
