"""Lab (nothing imports it): the scene fusion's voxel, truncation and face-rule tolerance, in pixel footprints (#59:
DTU's mesh at the CUDA plan's voxel of 0.8 footprints is rough and holed where the CPU plan's voxel of 2.6 footprints
gives a smooth one; design/decisions.md "Not changed: the scene fusion's grid and the face rule's tolerance"). One
CPU fit; at its end the same rendered depths are fused again per variant (lab/scene_fusion.py), each mesh written
beside the fit's and, for a scene with a truth, scored by the ROI F-score (0.5 % of the region's diagonal, as
lab/final_fusion.py and the peers' scorer); every variant's share of fused faces the face rule keeps, and how far
the views' depths disagree (:func:`disagreement`).

    SCENE_FUSION="K:T:F,..." PYTHONPATH=. .venv/bin/python lab/fusion_fp.py SCENE OUT [--views 48 --width 160
        --height 120] [--set K=V ...]

SCENE: a built-in or a name of benchmarks/peers/scenes.py (at --views, --width, --height), or a dataset's path
(../shared/data/dtu_scan24; no truth). K: the voxel as a multiple of the plan's (0.5: twice as fine; DTU's CPU plan
is 192, so 0.3333 is 576); T: truncation in voxels; F: the face rule's tolerance in voxels. Other lab patches by
their variables (lab/fit_patches.py: GEO_CONSISTENCY for lab/geo_consistency.py).
"""
import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.join(HERE, "..", "benchmarks", "peers")]

TEXTURED = 0.02  # grey-level std (of [0, 1]) of a 7 x 7 window from which a reference pixel counts as textured


def disagreement(cameras, depths, neighbours=4, stride=2, colors=None):
    """How far the views' depths disagree, in pixel footprints: each view's depth points (every ``stride``-th pixel)
    projected into its ``neighbours`` nearest views (by centre), their depth there (nearest pixel: about a quarter
    footprint of error on an inclined surface) against that view's own, where both have one. Occlusions count as
    disagreement, so the upper percentiles include them. With ``colors`` (each view's rendered [H, W, 3]), also split
    by the reference pixel's texture: the grey level's standard deviation in its 7 x 7 window at least ``TEXTURED``."""
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
        for j in np.argsort(np.linalg.norm(centres - centres[i], axis=1))[1:neighbours + 1]:
            cj, dj = cameras[j], depths[j]
            uv, z = cj.project(pts)
            u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            inside = (u >= 0) & (v >= 0) & (u < cj.width) & (v < cj.height) & (z > 0)
            zj = np.zeros_like(z)
            zj[inside] = dj[v[inside], u[inside]]
            m = inside & (zj > 0)
            out.append((z[m] - zj[m]) / (zj[m] / cj.K[0, 0]))
            if colors is not None:
                tex.append(t_ref[m])
    r = np.abs(np.concatenate(out))
    res = {"median_fp": float(np.median(r)), "p75_fp": float(np.percentile(r, 75)),
           "p90_fp": float(np.percentile(r, 90)), "share_within": {t: float((r <= t).mean()) for t in (1, 2, 4, 8, 16)}}
    if colors is not None:
        t = np.concatenate(tex)
        res["texture"] = {name: {"share": float(sel.mean()), "median_fp": float(np.median(r[sel])),
                                 "p75_fp": float(np.percentile(r[sel], 75))}
                          for name, sel in (("textured", t), ("untextured", ~t))}
    return res


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()

    import trimesh

    import fit_patches
    import scene_fusion
    import wtopo
    from wtopo import metrics
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig

    if os.path.isdir(a.scene):  # a dataset: no truth
        from wtopo.loaders import load_scene

        scene, truth = load_scene(a.scene), None
    else:
        from final_fusion import roi_scene

        scene, lo, hi, tau = roi_scene(a.scene, a.views, a.width, a.height)
        truth = scene.gt_mesh
    fit_patches.install_from_env()  # SCENE_FUSION (lab/scene_fusion.py), e.g. GEO_CONSISTENCY
    if not scene_fusion.variants():
        scene_fusion.install()  # for its depths: the disagreement below
    cfg = FitConfig()
    for s in ["runtime.device=cpu", "runtime.usd_every=0", *a.set]:
        _apply_set(cfg, s)
    res = wtopo.fit(scene, cfg, out_dir=a.out, progress=False)
    policy = next((e for e in res.report.get("events", []) if e.get("event") == "mesh_policy"), {})
    rows = [{"variant": "product", "mesh": "mesh.ply", "policy": policy}]
    rows += [{"variant": name, "mesh": f"mesh_{name}.ply", "policy": variant_policy}
             for name, variant_policy in scene_fusion.last.get("policy", {}).items()]
    for r in rows:
        faces = r.pop("policy", {}).get("faces", {})
        r.update(fused=faces.get("faces"), kept=faces.get("kept"))
        m = trimesh.load(os.path.join(a.out, r.pop("mesh")), process=False)
        r["faces"] = len(m.faces)
        if truth is not None:
            f = metrics.roi_f_score(m, truth, lo, hi, tau, n_samples=100_000, seed=0)
            r.update(f1=round(f.f_score, 4), precision=round(f.precision, 4), recall=round(f.recall, 4))
        print(json.dumps(r), flush=True)
    depths, colors = scene_fusion.last["depths"]
    dis = disagreement(scene_fusion.last["cameras"], depths, colors=colors)
    fp = float(res.plan.reasons["proxy_resolution"].split("footprint ")[1].split(" ")[0])  # the plan's, at the ROI
    out = {"scene": a.scene, "voxel": res.report["tsdf"]["final_bounds"]["voxel"], "footprint": fp,
           "disagreement": dis, "psnr": res.report.get("psnr"), "rows": rows}
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}), flush=True)
    with open(os.path.join(a.out, "fusion_fp.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
