"""Lab (nothing imports it): the plane-sweep stereo at a lower resolution than the fit's images (#60: the
initial surfels take 10.5 s of DTU's 97.5 s on an H200, the goal is 3 s). For each scene of the peers' set
with ground truth and for each downscale factor: seconds, confirmed points, their distance to the truth
(median and the share within 0.5 % of the region's diagonal) and the share of training pixels no point
explains (the pixels that seed background shells). The fit keeps ``init.num_points`` (5,000) of the points.

    PYTHONPATH=. .venv/bin/python lab/stereo_res.py [--scenes bunny_env chair_env] [--factors 1 1.5 2] [--views 24]
"""
import argparse
import json
import os
import sys
import time

import numpy as np
from scipy.spatial import cKDTree

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=["bunny_env", "chair_env", "mug_torus_env"])
    ap.add_argument("--factors", nargs="+", type=float, default=[1.0, 1.5, 2.0])
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()

    import scenes as peer_scenes
    import trimesh

    from wtopo import scenes as wtopo_scenes
    from wtopo.fitting.background import uncovered_pixels
    from wtopo.fitting.scene_kind import analyse_layout
    from wtopo.geometry.mvs import plane_sweep_points

    for name in a.scenes:
        scene = (peer_scenes.load(name) if name in peer_scenes.names() else wtopo_scenes.load(name)).normalized()
        layout = analyse_layout(scene)
        gt = scene.gt_mesh
        pts_gt, _ = trimesh.sample.sample_surface(gt, 2_000_000, seed=0)
        tree = cKDTree(pts_gt)
        diag = float(np.linalg.norm(np.asarray(layout.roi_upper) - np.asarray(layout.roi_lower)))
        for f in a.factors:
            s = scene.downscaled(f) if f > 1 else scene
            t = time.perf_counter()
            found = plane_sweep_points(s.cameras, s.images, layout.roi_lower, layout.roi_upper, near=layout.near,
                                       device=a.device, max_views=a.views)
            sec = time.perf_counter() - t
            d, _ = tree.query(found.points, workers=-1)
            inside = np.all((found.points >= layout.roi_lower) & (found.points <= layout.roi_upper), axis=1)
            unc = uncovered_pixels(scene.cameras, found.points, device=a.device)
            row = {"scene": name, "factor": f, "size": [s.cameras[0].width, s.cameras[0].height], "s": round(sec, 1),
                   "points": len(found.points), "median_dist_pct": round(100 * float(np.median(d)) / diag, 4),
                   "within_0.5pct": round(float(np.mean(d < 0.005 * diag)), 4),
                   "within_0.5pct_roi": round(float(np.mean(d[inside] < 0.005 * diag)), 4) if inside.any() else None,
                   "uncovered": round(float(np.mean([u.float().mean().item() for u in unc])), 4)}
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
