# SPDX-License-Identifier: Apache-2.0
"""Where one mesh is farther from the truth than another (#59: wtopo's bunny64 mesh against PGSR's).

    .venv/bin/python lab/gap_regions.py GT.ply A_MESH B_MESH [--clusters 6]

A_MESH and B_MESH: a .ply, or an .npz with ``v`` [V, 3] and ``f`` [F, 3] (how a device call brings a large mesh
back). For 300,000 area samples of the truth, each mesh's distance and side (the sign along the truth's normal)
are measured; the script prints each mesh's completeness and accuracy (% of the truth's diagonal, the scorer's
convention), how A's completeness is spread over distance bands, and where the 2 % of the truth's samples with
the largest A-minus-B difference lie (k-means clusters: centre, samples, both distances, A's share inside).
Nothing imports it.
"""

import argparse

import numpy as np
import torch
import trimesh
from scipy.cluster.vq import kmeans2

from wtopo.raycast import closest_faces


def _load(path: str) -> trimesh.Trimesh:
    if path.endswith(".npz"):
        d = np.load(path)
        return trimesh.Trimesh(d["v"].astype(np.float64), d["f"], process=False)
    return trimesh.load(path, process=False)


def closest_points(mesh: trimesh.Trimesh, pts: np.ndarray, reach: float):
    v = torch.as_tensor(np.asarray(mesh.vertices, np.float64))
    f = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64)
    _, dist, cp = closest_faces(v, f, torch.as_tensor(pts), max_distance=reach)
    return dist.numpy(), cp.numpy()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("gt")
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--clusters", type=int, default=6)
    args = ap.parse_args(argv)
    gt, a, b = _load(args.gt), _load(args.a), _load(args.b)
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    reach = 0.2 * diag
    pts, fi = trimesh.sample.sample_surface(gt, 300_000, seed=2)
    normals = gt.face_normals[fi]
    comp, side = {}, {}
    for name, m in (("A", a), ("B", b)):
        d, cp = closest_points(m, pts, reach)
        comp[name] = 100 * d / diag
        side[name] = np.sign(((cp - pts) * normals).sum(1))
        pm, _ = trimesh.sample.sample_surface(m, 300_000, seed=3)
        acc = 100 * closest_points(gt, pm, reach)[0] / diag
        print(f"{name}: completeness {comp[name].mean():.5f} % accuracy {acc.mean():.5f} % (Chamfer "
              f"{(comp[name].mean() + acc.mean()) / 2:.5f}); accuracy percentiles 50/90/99/99.9 "
              f"{np.round(np.percentile(acc, [50, 90, 99, 99.9]), 4)}")
    da, db = comp["A"], comp["B"]
    for lo, hi in ((0, 0.02), (0.02, 0.05), (0.05, 0.1), (0.1, 0.3), (0.3, np.inf)):
        s = (da >= lo) & (da < hi)
        print(f"A's completeness in [{lo}, {hi}) %: {s.mean():.3f} of the truth, {da[s].sum() / len(da):.5f} of its "
              f"mean; B there {db[s].mean() if s.any() else 0:.4f} %")
    diff = da - db
    worst = diff > np.percentile(diff, 98)
    print(f"A farther on {(diff > 0).mean():.2f} of the truth; the worst 2 % hold {diff[worst].sum() / diff.sum():.2f} "
          f"of the mean difference {diff.mean():.5f} %")
    centres, label = kmeans2(pts[worst], args.clusters, seed=0, minit="++")
    for k in range(args.clusters):
        s = label == k
        print(f"  around {np.round(centres[k], 3)}: {s.sum()} samples, A {da[worst][s].mean():.3f} %, "
              f"B {db[worst][s].mean():.3f} %, A inside on {(side['A'][worst][s] < 0).mean():.2f}")


if __name__ == "__main__":
    main()
