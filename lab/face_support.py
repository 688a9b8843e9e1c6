"""Lab (nothing imports it): drop the final mesh's faces the training views contradict or do not see.

On chair_env the mesh hangs a skirt below the seat that costs most of its ROI precision (benchmarks/peers.md).
This fits a scene once on the CPU and, at the end, counts for every vertex of the final mesh (internal frame) the
training views whose rendered median depth agrees with it within TOL (support) and the views that see past it by
more than TOL (free space: the view's surface lies behind the vertex), then drops faces by several rules and
scores each by the ROI F-score (0.5 % of the ROI diagonal), the package's mesh first.

    PYTHONPATH=. .venv/bin/python lab/face_support.py SCENE [--views 48 --width 160 --height 120]
"""
import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))


def counts(verts, cameras, depths, tol):
    support = np.zeros(len(verts), np.int64)
    free = np.zeros(len(verts), np.int64)
    for cam, dep in zip(cameras, depths):
        uv, z = cam.project(verts)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        d = np.zeros(len(verts))
        d[ok] = np.asarray(dep)[v[ok], u[ok]]
        seen = ok & (d > 0)
        support += seen & (np.abs(d - z) <= tol)
        free += seen & (d > z + tol)
    return support, free


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--out", default="/tmp/face_support")
    a = ap.parse_args()

    import wtopo
    from wtopo import metrics, scenes
    from wtopo.fitting import _final_mesh as F
    from wtopo.fitting import loop as L
    from wtopo.fitting import stages as S
    from wtopo.fitting.config import FitConfig

    kw = dict(n_views=a.views, resolution=(a.width, a.height))
    if a.scene in scenes.names():
        scene = scenes.load(a.scene, **kw)
    else:
        import scenes as peer_scenes
        scene = peer_scenes.load(a.scene, **kw)
    lo, hi = (np.asarray(b, np.float64) for b in scene.info["roi"])
    tau = 0.005 * float(np.linalg.norm(hi - lo))
    sim = scene.normalization()
    rows = []
    real = F.final_mesh

    def score(m, **row):
        f = metrics.roi_f_score(sim.to_world(m), scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
        rows.append({**row, "f1": f.f_score, "precision": f.precision, "recall": f.recall, "faces": len(m.faces)})
        print(json.dumps(rows[-1]), flush=True)

    def variants(surfels, cameras, cfg, **k):
        mesh = real(surfels, cameras, cfg, **k)
        score(mesh, rule="package")
        depths, _ = S.render_depths(k["render"], surfels, cameras)
        verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        vox = float(k["tsdf_info"]["final_bounds"]["voxel"])
        for tol_vox in (2.0, 4.0):
            sup, free = counts(verts, cameras, depths, tol_vox * vox)
            fs, ff = sup[faces].min(1), free[faces].max(1)
            rules = {f"support>={n}": fs >= n for n in (1, 2, 3)}
            rules.update({f"free<{n}": ff < n for n in (1, 2, 4)})
            rules["free<=support"] = free[faces].mean(1) <= sup[faces].mean(1)
            for name, keep in rules.items():
                m = mesh.copy()
                m.update_faces(keep)
                m.remove_unreferenced_vertices()
                score(m, rule=name, tol_voxels=tol_vox)
        return mesh

    L.final_mesh = variants
    cfg = FitConfig()
    cfg.runtime.device = "cpu"
    cfg.runtime.usd_every = 0
    res = wtopo.fit(scene, cfg, progress=False)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, f"{a.scene}.json"), "w") as f:
        json.dump({"scene": a.scene, "psnr": res.report.get("psnr"), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
