"""Lab (nothing imports it): the scene fusion's voxel, truncation and face-rule tolerance on scenes with a truth, in
pixel footprints (#59: DTU's mesh at the CUDA plan's voxel of 0.8 footprints is rough and full of holes where the
CPU plan's voxel of 2.6 footprints gives a smooth one; lab/dtu_fusion.py). One CPU fit per scene; at its end the
same rendered depths are fused again per variant (lab/scene_fusion.py) and each mesh is scored by the ROI F-score
(0.5 % of the region's diagonal, as lab/final_fusion.py and the peers' scorer).

    SCENE_FUSION="K:T:F,..." PYTHONPATH=. .venv/bin/python lab/fusion_fp.py SCENE OUT [--views 48 --width 160
        --height 120] [--set K=V ...]

K: the voxel as a multiple of the plan's (0.5: twice as fine); T: truncation in voxels; F: the face rule's tolerance
in voxels. Prints the plan's footprint and voxel so that each variant reads in footprints.
"""
import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.join(HERE, "..", "benchmarks", "peers")]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()

    import numpy as np
    import trimesh

    import scene_fusion
    import wtopo
    from wtopo import metrics, scenes
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig

    kw = dict(n_views=a.views, resolution=(a.width, a.height))
    if a.scene in scenes.names():
        scene = scenes.load(a.scene, **kw)
    else:
        import scenes as peer_scenes
        scene = peer_scenes.load(a.scene, **kw)
    lo, hi = (np.asarray(b, np.float64) for b in scene.info["roi"])
    tau = 0.005 * float(np.linalg.norm(hi - lo))
    import fit_patches

    fit_patches.install_from_env()  # SCENE_FUSION (lab/scene_fusion.py), e.g. GEO_CONSISTENCY (geo_consistency.py)
    if not scene_fusion.variants():
        scene_fusion.install()  # for its depths: the disagreement below
    cfg = FitConfig()
    for s in ["runtime.device=cpu", "runtime.usd_every=0", *a.set]:
        _apply_set(cfg, s)
    res = wtopo.fit(scene, cfg, out_dir=a.out, progress=False)
    plan = res.plan
    fb = res.report["tsdf"]["final_bounds"]
    fp = float(plan.reasons["proxy_resolution"].split("footprint ")[1].split(" ")[0])  # the plan's, at the ROI
    rows = [{"variant": "product", "mesh": os.path.join(a.out, "mesh.ply")}]
    rows += [{"variant": scene_fusion._name(*v), "mesh": os.path.join(a.out, f"mesh_{scene_fusion._name(*v)}.ply")}
             for v in scene_fusion.variants()]
    for r in rows:
        m = trimesh.load(r.pop("mesh"), process=False)
        f = metrics.roi_f_score(m, scene.gt_mesh, lo, hi, tau, n_samples=100_000, seed=0)
        r.update(f1=round(f.f_score, 4), precision=round(f.precision, 4), recall=round(f.recall, 4),
                 faces=len(m.faces))
        print(json.dumps(r), flush=True)
    from dtu_fusion import disagreement

    depths, colors = scene_fusion.last["depths"]
    dis = disagreement(scene_fusion.last["cameras"], depths, colors=colors)
    print(json.dumps({"disagreement": dis}), flush=True)
    out = {"scene": a.scene, "voxel": fb["voxel"], "footprint": fp, "disagreement": dis, "psnr": res.report.get("psnr"),
           "rows": rows}
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}), flush=True)
    with open(os.path.join(a.out, "fusion_fp.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
