"""Lab (nothing imports it): DTU scan24's held-out view 40, where wtopo's render loses 4-10 dB to gsplat's on the GPU
(`benchmarks/peers.md`). One CPU fit at the default on the peers' split (every 8th view held out), then every
held-out view rendered with the fit's filter: all surfels, without those outside the region of interest (the
background shells and whatever they became), and only those that contribute to a pixel of some training view; PSNR
per view, and a picture of view 40: the photo, the three renders and their errors (x4).

    PYTHONPATH=. .venv/bin/python lab/dtu_view40.py [--data ../shared/data/dtu_scan24] [--out /tmp/dtu_view40.png]
"""
import argparse
import json
import os
import sys

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)


def peers_split(path):
    """DTU at ``path`` with the peers harness's split (every eighth view held out): ``(scene, held-out indices)``."""
    import wtopo

    scene = wtopo.load_scene(path)
    n = len(scene.cameras)
    test = list(range(0, n, 8))
    return scene._replace(train_indices=[i for i in range(n) if i not in test], test_indices=test), test


def black_shells() -> None:
    """Patch the fit (this process only) so that the background shells start black: their colour is otherwise the
    pixel's each was seeded from, which behind an untextured near surface (DTU's white table) is that surface's."""
    from wtopo.fitting import _init_surfels as init

    real = init.background_surfels

    def shells(*args, **kw):
        s = real(*args, **kw)
        with torch.no_grad():
            s.params["sh_dc"].fill_(-0.5 / 0.28209479177387814)  # RGB 0 through the SH's DC term
        return s

    init.background_surfels = shells


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=os.path.join(HERE, "..", "..", "shared", "data", "dtu_scan24"))
    ap.add_argument("--out", default="/tmp/dtu_view40.png")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--save", default=None, help="also torch.save the fitted surfels (internal frame) to this path")
    ap.add_argument("--hard-views", type=float, default=0.0,
                    help="experiment: draw each iteration's view with probability ~ (its photometric loss EMA)^this")
    ap.add_argument("--black-shells", action="store_true",
                    help="experiment: the background shells start black (the scene's background) instead of the "
                         "colour of the pixel each was seeded from")
    a = ap.parse_args()
    if a.black_shells:
        black_shells()
    if a.hard_views:
        from hard_views import install

        install(a.hard_views, a.seed)

    from PIL import Image

    import wtopo
    from wtopo import ops
    from wtopo.cli import _apply_set
    from wtopo.fitting.background import BackgroundState
    from wtopo.fitting.config import FitConfig

    scene, test = peers_split(a.data)
    cfg = FitConfig()
    for item in ["runtime.device=cpu", "runtime.usd_every=0", f"runtime.seed={a.seed}", *a.set]:
        _apply_set(cfg, item)
    res = wtopo.fit(scene, cfg, progress=False)
    s = res.surfels
    inner = scene.normalized()
    if a.save:
        torch.save({"means": s.means, "quats": s.quats, "scales": s.scales, "opacities": s.opacities, "sh": s.sh,
                    "sh_degree": s.sh_degree, "filter_sigma": res.plan.filter_sigma}, a.save)
    outside = BackgroundState(res.plan.layout, s.means.device).outside_roi(s.means)
    raster = ops.RasterConfig(filter_sigma=res.plan.filter_sigma)
    # the surfels that contribute to no pixel of any training view: no photograph supports them
    seen = torch.zeros(len(s.means), dtype=torch.bool)
    for i in scene.train_indices:
        with torch.no_grad():
            r = ops.rasterize_surfels(s.means, s.quats, s.scales, s.opacities, s.sh, inner.cameras[i],
                                      sh_degree=s.sh_degree, config=raster)
        seen |= r.visibility > 0
    rows, tiles = [], None
    for i in test:
        photo = inner.images[i].numpy()
        out = []
        for keep in (torch.ones_like(outside), ~outside, seen):
            with torch.no_grad():
                r = ops.rasterize_surfels(s.means[keep], s.quats[keep], s.scales[keep], s.opacities[keep], s.sh[keep],
                                          inner.cameras[i], sh_degree=s.sh_degree, config=raster)
            out.append(r.rgb.clamp(0, 1).numpy())
        psnr = [float(-10 * np.log10(np.mean((o - photo) ** 2))) for o in out]
        rows.append({"view": i, "psnr": round(psnr[0], 2), "psnr_without_outside": round(psnr[1], 2),
                     "psnr_seen_only": round(psnr[2], 2)})
        if i == 40:
            err = [np.clip(4 * np.abs(o - photo), 0, 1) for o in out]
            tiles = np.concatenate([photo, *out, *err], axis=1)
    print(json.dumps({"surfels": int(len(s.means)), "outside_roi": int(outside.sum()), "unseen": int((~seen).sum()),
                      "report_psnr": res.report.get("psnr"), "views": rows}), flush=True)
    if tiles is not None:
        Image.fromarray((tiles * 255).astype(np.uint8)).save(a.out)


if __name__ == "__main__":
    main()
