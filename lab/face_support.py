"""Lab (nothing imports it): drop the final mesh's faces the training views contradict or do not see.

On chair_env the mesh hangs a skirt below the seat that costs most of its ROI precision (benchmarks/peers.md).
This fits a scene once on the CPU and, at the end, takes the final mesh before the package's face rule
(geometry.mesh_policy.supported_faces) and counts for every vertex (internal frame) the training views whose
rendered median depth agrees with it within twice the fusion voxel: at one of the four pixel centres around its
projection (2x2), or at the pixel it falls in (floor). Faces go by each rule (min views at every vertex;
optionally only unsupported regions of at least an area in fusion voxels squared) and each mesh is scored by the
ROI F-score (0.5 % of the ROI diagonal): none, the package's rule, then the variants. The free-space rules
measured before lost recall (design/decisions.md).

    PYTHONPATH=. .venv/bin/python lab/face_support.py SCENE [--views 48 --width 160 --height 120]
"""
import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))


def footprint(verts, cam, dep, tol, how="2x2"):
    """Per vertex: a view agrees when the pixel it falls in (floor) or one of the four pixel centres around the
    projection (2x2) has a positive depth within tol of the vertex's z."""
    uv, z = cam.project(verts)
    h, w = dep.shape[:2]
    if how == "floor":
        offsets, u0, v0 = [(0, 0)], np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    else:
        offsets = [(0, 0), (0, 1), (1, 0), (1, 1)]
        u0 = np.floor(uv[:, 0] - 0.5).astype(np.int64)
        v0 = np.floor(uv[:, 1] - 0.5).astype(np.int64)
    agree = np.zeros(len(verts), bool)
    for du, dv in offsets:
        u, v = u0 + du, v0 + dv
        ok = np.flatnonzero((z > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h))
        d = dep[v[ok], u[ok]]
        agree[ok[(d > 0) & (np.abs(d - z[ok]) <= tol)]] = True
    return agree


def support_counts(verts, cameras, depths, tol, how):
    sup = np.zeros(len(verts), np.int64)
    for cam, dep in zip(cameras, depths):
        sup += footprint(verts, cam, np.asarray(dep), tol, how)
    return sup


def region_filter(verts, faces, drop, min_area):
    """Only unsupported regions (faces joined by vertices) of at least min_area go."""
    from wtopo.geometry.components import face_components
    idx = np.flatnonzero(drop)
    if len(idx) == 0 or min_area <= 0:
        return drop
    n, lab = face_components(faces[idx], len(verts))
    tri = verts[faces[idx]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    region = np.bincount(lab, weights=area, minlength=n)
    out = np.zeros(len(faces), bool)
    out[idx[region[lab] >= min_area]] = True
    return out


def variants_of(verts, faces, cameras, depths, tol, voxel):
    """Every rule's kept-face mask, by name (regions: least area in fusion voxels squared)."""
    rules = {}
    for how in ("floor", "2x2"):
        fs = support_counts(verts, cameras, depths, tol, how)[faces].min(1)
        for mv in (2, 3):
            drop = fs < mv
            rules[f"{how} min{mv}"] = ~drop
            for vox2 in (25, 100, 400):
                rules[f"{how} min{mv} regions>={vox2}vox2"] = ~region_filter(verts, faces, drop, vox2 * voxel ** 2)
    return rules


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--out", default="/tmp/face_support")
    a = ap.parse_args()

    import wtopo
    from final_fusion import roi_scene
    from wtopo import metrics
    from wtopo.fitting import _final_mesh as F
    from wtopo.fitting import loop as L
    from wtopo.fitting import stages as S
    from wtopo.fitting.config import FitConfig

    scene, lo, hi, tau = roi_scene(a.scene, a.views, a.width, a.height)
    sim = scene.normalization()
    rows = []
    real = F.final_mesh

    def score(m, **row):
        f = metrics.roi_f_score(sim.to_world(m), scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
        rows.append({**row, "f1": f.f_score, "precision": f.precision, "recall": f.recall, "faces": len(m.faces)})
        print(json.dumps(rows[-1]), flush=True)

    def variants(surfels, cameras, cfg, **k):
        F.supported_faces = lambda mesh, *args, **kw: (mesh, {})  # the mesh before the package's face rule
        try:
            mesh = real(surfels, cameras, cfg, **k)
        finally:
            F.supported_faces = package_rule
        score(mesh, rule="none")
        depths, _ = S.render_depths(k["render"], surfels, cameras)
        verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        vox = float(k["tsdf_info"]["final_bounds"]["voxel"])
        tol = F._FACE_SUPPORT_VOXELS * vox
        score(package_rule(mesh, cameras, depths, tol)[0], rule="package")
        for name, keep in variants_of(verts, faces, cameras, depths, tol, vox).items():
            m = mesh.copy()
            m.update_faces(keep)
            m.remove_unreferenced_vertices()
            score(m, rule=name)
        return mesh

    package_rule = F.supported_faces
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
