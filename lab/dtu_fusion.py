"""Lab (nothing imports it): why DTU's scene mesh is rough and full of holes on the GPU and smooth on the CPU.

The scene's final mesh fuses each training view's rendered median depth at a voxel of 0.8 pixel footprints (the plan's
``_FINAL_FOOTPRINTS``) with a truncation of 4 voxels, clipped to the device's final grid: 96-192 voxels on the CPU,
where DTU's voxel is 2.6 footprints, up to 768 on CUDA, where it is 0.8. This fits DTU scan24 once on the CPU and, at
the end, measures how far the views' depths disagree (each view's depth points reprojected into its nearest views, in
pixel footprints) and fuses the same depths at the grids, truncations and face-rule tolerances of VARIANTS (--only:
their indices), writing each mesh (world frame) and the share of its faces the per-face view-support rule keeps
(design/decisions.md, "Not changed: the scene fusion's grid and the face rule's tolerance").

    PYTHONPATH=. .venv/bin/python lab/dtu_fusion.py ../shared/data/dtu_scan24 OUT [--only I ...] [--set K=V ...]
"""
import argparse
import dataclasses
import json
import os
import time

import numpy as np

# (final grid or None for the plan's, truncation in voxels, the face rule's tolerance in voxels)
TEXTURED = 0.02  # grey-level std (of [0, 1]) of a 7 x 7 window from which a reference pixel counts as textured
VARIANTS = ((None, 4.0, 2.0), (576, 4.0, 2.0), (576, 8.0, 2.0), (576, 12.0, 2.0), (384, 6.0, 2.0), (576, 4.0, 5.0),
            (576, 4.0, 1e6))


def disagreement(cameras, depths, neighbours=4, stride=2, colors=None):
    """How far the views' depths disagree, in pixel footprints: each view's depth points (every ``stride``-th pixel)
    projected into its ``neighbours`` nearest views (by centre), their depth there against that view's own, where
    both have one. Occlusions count as disagreement, so the upper percentiles include them. With ``colors`` (each
    view's rendered [H, W, 3]), also split by the reference pixel's texture: the grey level's standard deviation in
    its 7 x 7 window at least ``TEXTURED`` or not."""
    from scipy.ndimage import uniform_filter

    centres = np.stack([c.center for c in cameras])
    out, tex = [], []
    for i, (ci, di) in enumerate(zip(cameras, depths)):
        o, d = ci.pixel_rays()
        o, d = o.numpy()[::stride, ::stride], d.numpy()[::stride, ::stride]
        di = di[::stride, ::stride]
        ok = di > 0
        if colors is not None:
            g = colors[i].mean(-1).astype(np.float64)
            std = np.sqrt(np.maximum(uniform_filter(g * g, 7) - uniform_filter(g, 7) ** 2, 0))[::stride, ::stride]
            t_ref = (std >= TEXTURED)[ok]
        pts = (o + d * di[..., None])[ok]
        near = np.argsort(np.linalg.norm(centres - centres[i], axis=1))[1:neighbours + 1]
        for j in near:
            cj, dj = cameras[j], depths[j]
            uv, z = cj.project(pts)
            u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (u >= 0) & (v >= 0) & (u < cj.width) & (v < cj.height) & (z > 0)
            zj = np.zeros_like(z)
            zj[inside] = dj[v[inside], u[inside]]
            m = inside & (zj > 0)
            fp = zj[m] / cj.K[0, 0]
            out.append((z[m] - zj[m]) / fp)
            if colors is not None:
                tex.append(t_ref[m])
    r = np.abs(np.concatenate(out))
    if colors is not None:
        t = np.concatenate(tex)
        split = {name: {"share": float(sel.mean()), "median_fp": float(np.median(r[sel])),
                        "p75_fp": float(np.percentile(r[sel], 75))}
                 for name, sel in (("textured", t), ("untextured", ~t))}
    return {**({"texture": split} if colors is not None else {}), "median_fp": float(np.median(r)),
            "p75_fp": float(np.percentile(r, 75)), "p90_fp": float(np.percentile(r, 90)),
            "share_within": {t: float((r <= t).mean()) for t in (1, 2, 4, 8, 16)}}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--only", type=int, nargs="*", help="indices of VARIANTS to run")
    a = ap.parse_args()

    import fit_patches
    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting import _final_mesh as F
    from wtopo.fitting import loop as L
    from wtopo.fitting.config import FitConfig
    from wtopo.loaders import load_scene

    scene = load_scene(a.scene)
    sim = scene.normalization()
    os.makedirs(a.out, exist_ok=True)
    real = F.final_mesh
    rows = []

    def variants(surfels, cameras, cfg, **k):
        saved = (F.render_depths, F.TRUNCATION_VOXELS, F._FACE_SUPPORT_VOXELS)
        depths, colors = saved[0](k["render"], surfels, cameras)
        np.savez_compressed(os.path.join(a.out, "depths.npz"), *depths)
        dis = disagreement(cameras, depths, colors=colors)
        print(json.dumps({"disagreement": dis}), flush=True)
        rows.append({"disagreement": dis})
        F.render_depths = lambda *_: (depths, colors)
        base = int(cfg.final.resolution)
        try:
            for res, tr, face in [v for i, v in enumerate(VARIANTS) if a.only is None or i in a.only]:
                res = res or base
                F.TRUNCATION_VOXELS = tr
                F._FACE_SUPPORT_VOXELS = face
                c = dataclasses.replace(cfg, final=dataclasses.replace(cfg.final, resolution=res))
                events = []
                t0 = time.perf_counter()
                m = real(surfels, cameras, c, **{**k, "tsdf_info": {},
                                                 "record": lambda e, ev=events, **kw: ev.append((e, kw))})
                info = {e: kw for e, kw in events}.get("mesh_policy", {})
                row = {"resolution": res, "truncation_voxels": tr, "face_voxels": face, "faces": len(m.faces),
                       "fused": info.get("faces", {}).get("faces"), "kept": info.get("faces", {}).get("kept"),
                       "components": info.get("components", {}).get("kept"), "seconds": time.perf_counter() - t0}
                rows.append(row)
                print(json.dumps(row), flush=True)
                sim.to_world(m).export(os.path.join(a.out, f"mesh_{res}_{tr:g}_{face:g}.ply"))
        finally:
            F.render_depths, F.TRUNCATION_VOXELS, F._FACE_SUPPORT_VOXELS = saved
        return real(surfels, cameras, cfg, **k)

    fit_patches.install_from_env()  # e.g. GEO_CONSISTENCY (lab/geo_consistency.py)
    L.final_mesh = variants
    cfg = FitConfig()
    for s in ["runtime.device=cpu", "runtime.usd_every=0", *a.set]:
        _apply_set(cfg, s)
    t0 = time.perf_counter()
    res = wtopo.fit(scene, cfg, progress=False)
    out = {"fit_s": time.perf_counter() - t0, "psnr": res.report.get("psnr"), "rows": rows}
    with open(os.path.join(a.out, "rows.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
