"""Lab (nothing imports it): where a scene mesh's ROI precision and recall are lost.

Samples the predicted mesh inside the scene's region of interest as the ROI F-score does (wtopo.metrics.roi_f_score),
and sorts the samples farther than tau from the truth by the truth's face they are nearest to: flat (face normal
within 30 degrees of the up axis: the ground, and any horizontal face of the objects, such as a chair's seat) or
not; for the mesh's samples, whether they lie above the truth along the up axis, and how far in units of tau. The
same for the ground-truth samples the mesh misses.

    PYTHONPATH=. .venv/bin/python lab/roi_where.py SCENE MESH.ply [--views 48 --width 160 --height 120]
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "peers"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("mesh")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    a = ap.parse_args()
    import scenes as peer_scenes
    import trimesh

    from wtopo import scenes
    from wtopo.metrics._scene import _sample_in_box
    from wtopo.metrics._surface import _Surface

    kw = dict(n_views=a.views, resolution=(a.width, a.height))
    scene = scenes.load(a.scene, **kw) if a.scene in scenes.names() else peer_scenes.load(a.scene, **kw)
    lo, hi = (np.asarray(b, np.float64) for b in scene.info["roi"])
    tau = 0.005 * float(np.linalg.norm(hi - lo))
    gt_mesh = scene.gt_mesh
    pred = trimesh.load(a.mesh, process=False)
    gt = _Surface("gt", gt_mesh, 0, 0)
    pr = _Surface("pred", (np.asarray(pred.vertices), np.asarray(pred.faces)), 0, 0)
    up = np.asarray(scene.info.get("up", (0.0, 0.0, 1.0)), np.float64)
    up /= np.linalg.norm(up)
    gn = np.asarray(gt_mesh.face_normals)
    ground_face = np.abs(gn @ up) > np.cos(np.radians(30))
    print(f"{a.scene}: tau {tau:.5f}, up {up.round(3).tolist()}")
    for name, src, dst in (("precision (mesh samples)", pred, gt), ("recall (truth samples)", gt_mesh, pr)):
        pts = _sample_in_box(np.asarray(src.vertices), np.asarray(src.faces), lo, hi, 200_000, 1)
        surf = dst if isinstance(dst, _Surface) else gt
        d, fi = surf.closest(pts)
        bad = d > tau
        print(f"{name}: {len(pts)} samples, {bad.mean():.3f} beyond tau")
        if name.startswith("precision"):
            on_ground = ground_face[fi]
        else:
            _, gfi = gt.closest(pts)
            on_ground = ground_face[gfi]
        for label, sel in (("flat", on_ground), ("other", ~on_ground)):
            s = bad & sel
            share = s.sum() / max(1, sel.sum())
            line = f"  {label:6s}: {sel.mean():.3f} of the samples, {share:.3f} of them beyond tau"
            if name.startswith("precision") and s.any():
                cp = gt.closest_points(pts[s])
                off = ((pts[s] - cp) @ up) / tau
                ratio = d[s] / tau
                line += (f"; above the truth {np.mean(off > 0):.2f}; distance / tau: median {np.median(ratio):.1f}, "
                         f"p90 {np.percentile(ratio, 90):.1f}")
            print(line)


if __name__ == "__main__":
    main()
