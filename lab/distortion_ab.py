"""Lab (nothing imports it): the depth-distortion weight (losses.distortion) at 100 and at 2DGS's DTU value 1000,
one CPU fit per scene and weight, in sequence. Per fit: held-out PSNR, the fit's own Chamfer / F-score where the
scene has a ground truth and no region of interest, the ROI F-score (0.5 % of the ROI diagonal) where it has one,
and the share of the fused faces the per-face view-support rule keeps (how well the views' rendered depths agree).
DTU scan24 is read from ../shared/data at half size.

    PYTHONPATH=. .venv/bin/python lab/distortion_ab.py bunny chair_env bunny_env dtu [--weights 100 1000] [--seed 0]
"""
import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))
DTU = os.path.join(HERE, "..", "..", "shared", "data", "dtu_scan24")


def load(name):
    from wtopo import scenes
    if name == "dtu":
        from wtopo import load_scene
        return load_scene(DTU)
    if name in ("chair_env", "mug_torus_env"):
        import scenes as peer_scenes
        return peer_scenes.load(name, n_views=48, resolution=(160, 120))
    if name == "bunny_env":
        return scenes.load(name, n_views=48, resolution=(160, 120))
    return scenes.load(name)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--weights", type=float, nargs="+", default=[100.0, 1000.0])
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()

    import wtopo
    from wtopo import metrics
    from wtopo.fitting.config import FitConfig

    for name in a.scenes:
        for w in a.weights:
            scene = load(name)
            cfg = FitConfig()
            cfg.runtime.device = "cpu"
            cfg.runtime.usd_every = 0
            cfg.runtime.seed = a.seed
            cfg.losses.distortion = w
            if name == "dtu":
                cfg.runtime.image_scale = 0.5
            res = wtopo.fit(scene, cfg, progress=False)
            rep = res.report
            ev = [e for e in rep.get("events", []) if e.get("event") == "mesh_policy"]
            faces = ev[-1].get("faces") if ev else None
            row = {"scene": name, "distortion": w, "seed": a.seed, "psnr": rep.get("psnr"),
                   "elapsed_s": rep.get("elapsed_s"), "faces": rep["mesh"]["faces"],
                   "face_rule_kept": None if not faces else round(faces["kept"] / max(faces["faces"], 1), 4)}
            roi = (scene.info or {}).get("roi") if hasattr(scene, "info") else None
            if roi is not None and scene.gt_mesh is not None:
                lo, hi = (np.asarray(b, np.float64) for b in roi)
                tau = 0.005 * float(np.linalg.norm(hi - lo))
                f = metrics.roi_f_score(res.mesh, scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
                row.update(roi_f1=f.f_score, roi_p=f.precision, roi_r=f.recall)
            elif rep.get("chamfer") is not None:
                row.update(chamfer_pct=100 * rep["chamfer"], f_score=rep.get("f_score"))
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
