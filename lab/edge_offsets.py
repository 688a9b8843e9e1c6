# SPDX-License-Identifier: Apache-2.0
"""Where a mesh lies inside or outside the truth, by distance from the truth's sharp edges (#59: the outline offset
moves the chairs outward, lab/hard.md "outline on the chair"). Nothing imports it.

    PYTHONPATH=. .venv/bin/python lab/edge_offsets.py EXCH MESH [MESH ...]

EXCH: an exchange folder of benchmarks/peers/export.py (its ``gt.ply``); MESH: a mesh in that frame. 200,000 area
samples of the truth; each one's signed distance to the mesh (+ outside, along the truth's normal, % of the
truth's diagonal), grouped by the sample's distance from the nearest sharp edge of the truth (dihedral angle above
60 degrees): rounded edges read inside, a surface offset reads the same in every group.
"""

import os
import sys

import numpy as np
import trimesh
from scipy.spatial import cKDTree

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.join(HERE, "..", "benchmarks", "peers")]
import exchange  # noqa: E402

from gap_regions import closest_points  # noqa: E402

BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 1.0), (1.0, np.inf))  # distance from a sharp edge, % of the diagonal


def main(root: str, paths: list[str]) -> None:
    gt = exchange.load(root).gt()
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    pts, fi = trimesh.sample.sample_surface(gt, 200_000, seed=2)
    nrm = gt.face_normals[fi]
    sharp = gt.face_adjacency_angles > np.radians(60)
    ends = gt.vertices[gt.face_adjacency_edges[sharp]]  # [K, 2, 3]
    t = np.linspace(0.0, 1.0, 20)[None, :, None]
    along = (ends[:, :1] * (1 - t) + ends[:, 1:] * t).reshape(-1, 3)
    d_edge = 100 * cKDTree(along).query(pts)[0] / diag if len(along) else np.full(len(pts), np.inf)
    for path in paths:
        dist, cp = closest_points(trimesh.load(path, process=False), pts, 0.2 * diag)
        s = np.sign(((cp - pts) * nrm).sum(1)) * 100 * dist / diag
        print(f"{path}: {int(sharp.sum())} sharp edges")
        for lo, hi in BANDS:
            sel = (d_edge >= lo) & (d_edge < hi)
            if sel.any():
                print(f"  [{lo}, {hi}) % from a sharp edge: {100 * sel.mean():.0f} % of the truth, signed mean "
                      f"{s[sel].mean():+.4f} median {np.median(s[sel]):+.4f}, unsigned {np.abs(s[sel]).mean():.4f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
