"""Lab (nothing imports it): the scene mesh's final fusion, truncation and voxel, scored by the ROI F-score.

The DTU scene mesh is layered and speckled where the peers' are continuous (benchmarks/peers.md). The final mesh of a
scene is a TSDF of the surfels' rendered median depth over the region of interest, TRUNCATION_VOXELS voxels either
side, at the planned final resolution. This fits an unbounded synthetic scene once on the CPU and, at the end, fuses
the same rendered depths again with other truncations and voxels, scoring every variant (the ROI precision, recall
and F1 at 0.5 % of the region's diagonal, as benchmarks/real.py and the peers' scorer do).

    PYTHONPATH=. .venv/bin/python lab/final_fusion.py SCENE [--views 48 --width 160 --height 120] [--set K=V ...]

SCENE: a built-in (bunny_env) or a name of benchmarks/peers/scenes.py (chair_env, mug_torus_env).

--depths: instead, fuse at the planned truncation and voxel the median depth (the package's) and the expected
depth (alpha-normalised mean of the contributions: what 2DGS fuses for unbounded scenes, its depth_ratio 0), each
where the rendered opacity reaches 0.5.
"""
import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

TRUNCATIONS = (2.0, 4.0, 8.0, 12.0)
RESOLUTION_FACTORS = (1.0, 0.5)


def roi_scene(name: str, views: int, width: int, height: int):
    """A scene with a truth (a built-in, or a name of benchmarks/peers/scenes.py) at ``views`` views of ``width`` x
    ``height``, its region of interest (lo, hi) and the ROI F-score's tau (0.5 % of the region's diagonal)."""
    from wtopo import scenes

    kw = dict(n_views=views, resolution=(width, height))
    if name in scenes.names():
        scene = scenes.load(name, **kw)
    else:
        import scenes as peer_scenes
        scene = peer_scenes.load(name, **kw)
    lo, hi = (np.asarray(b, np.float64) for b in scene.info["roi"])
    return scene, lo, hi, 0.005 * float(np.linalg.norm(hi - lo))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--out", default="/tmp/final_fusion")
    ap.add_argument("--depths", action="store_true", help="median against expected depth, planned grid")
    ap.add_argument("--save-meshes", action="store_true", help="write each scored mesh (world frame) to --out")
    a = ap.parse_args()

    import wtopo
    from wtopo import metrics
    from wtopo.cli import _apply_set
    from wtopo.fitting import _final_mesh as F
    from wtopo.fitting import loop as L
    from wtopo.fitting.config import FitConfig

    scene, lo, hi, tau = roi_scene(a.scene, a.views, a.width, a.height)
    sim = scene.normalization()
    rows = []
    real = F.final_mesh

    import torch

    from wtopo.fitting import stages as S

    def expected_depths(render, surfels, cameras):
        depths, colors = [], []
        with torch.no_grad():
            for cam in cameras:
                out = render(surfels, cam)
                d = torch.where(out.alpha >= S.ALPHA_THRESHOLD, out.depth, torch.zeros_like(out.depth))
                depths.append(d.cpu().numpy())
                colors.append(out.rgb.clamp(0, 1).cpu().numpy())
        return depths, colors

    def score(m, **row):
        world = sim.to_world(m)
        if a.save_meshes:
            os.makedirs(a.out, exist_ok=True)
            world.export(os.path.join(a.out, f"{a.scene}_{'_'.join(str(v) for v in row.values())}.ply"))
        f = metrics.roi_f_score(world, scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
        rows.append({**row, "f1": f.f_score, "precision": f.precision, "recall": f.recall, "faces": len(m.faces)})
        print(json.dumps(rows[-1]), flush=True)

    def depth_variants(surfels, cameras, cfg, **k):
        for name, fn in (("expected", expected_depths), ("median", S.render_depths)):
            F.render_depths = fn
            try:
                m = real(surfels, cameras, cfg, **{**k, "tsdf_info": {}})
            finally:
                F.render_depths = S.render_depths
            score(m, depth=name)
        return m

    def variants(surfels, cameras, cfg, **k):
        base_res = int(cfg.final.resolution)
        for fac in RESOLUTION_FACTORS:
            for tr in TRUNCATIONS:
                F.TRUNCATION_VOXELS = tr
                c = dataclasses.replace(cfg, final=dataclasses.replace(cfg.final, resolution=int(base_res * fac)))
                t0 = time.perf_counter()
                try:
                    m = real(surfels, cameras, c, **{**k, "tsdf_info": {}})
                except Exception as e:  # noqa: BLE001 - an empty variant is a result too
                    rows.append({"resolution": int(base_res * fac), "truncation": tr, "error": str(e)})
                    continue
                dt = time.perf_counter() - t0
                world = sim.to_world(m)
                f = metrics.roi_f_score(world, scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
                rows.append({"resolution": int(base_res * fac), "truncation": tr, "f1": f.f_score,
                             "precision": f.precision, "recall": f.recall, "faces": len(m.faces),
                             "components": int(len(m.split(only_watertight=False))) if len(m.faces) < 2_000_000
                             else None, "seconds": dt})
                print(json.dumps(rows[-1]), flush=True)
        F.TRUNCATION_VOXELS = 4.0
        return real(surfels, cameras, cfg, **k)

    L.final_mesh = depth_variants if a.depths else variants
    cfg = FitConfig()
    for s in ["runtime.device=cpu", "runtime.usd_every=0", *a.set]:
        _apply_set(cfg, s)
    t0 = time.perf_counter()
    res = wtopo.fit(scene, cfg, progress=False)
    out = {"scene": a.scene, "fit_s": time.perf_counter() - t0, "psnr": res.report.get("psnr"), "rows": rows}
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, f"{a.scene}.json"), "w") as f:
        json.dump(out, f, indent=1)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}))


if __name__ == "__main__":
    main()
