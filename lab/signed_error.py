# SPDX-License-Identifier: Apache-2.0
"""Which side of the truth a mesh lies on (#59: why the authors' bunny64 mesh is closer than wtopo's).

    .venv/bin/python lab/signed_error.py TRUTH.ply MESH.ply [MESH.ply ...]

For each mesh: 300,000 points sampled on its surface, each one's distance to the nearest of 3,000,000 points
sampled on the truth, signed by that truth face's normal (+ outside), as % of the truth's bounding-box diagonal;
and the completeness the other way (300,000 of the truth's points to the mesh's samples). A lab measurement: its
samples are not the scorer's (benchmarks/peers/score.py), so its means are not the table's Chamfer. Nothing
imports it.
"""

import sys

import numpy as np
import trimesh
from scipy.spatial import cKDTree


def main(truth_path: str, mesh_paths: list[str]) -> None:
    truth = trimesh.load(truth_path, force="mesh")
    diag = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
    tp, ti = trimesh.sample.sample_surface(truth, 3_000_000, seed=1)
    tn = truth.face_normals[ti]
    tree = cKDTree(tp)
    for path in mesh_paths:
        mesh = trimesh.load(path, force="mesh")
        pts, _ = trimesh.sample.sample_surface(mesh, 300_000, seed=0)
        d, i = tree.query(pts)
        signed = np.sign(np.einsum("ij,ij->i", pts - tp[i], tn[i])) * d / diag * 100.0
        a = np.abs(signed)
        dc, _ = cKDTree(pts).query(tp[::10])
        c = dc / diag * 100.0
        print(f"{path}: accuracy mean {a.mean():.4f} median {np.median(a):.4f} p90 {np.percentile(a, 90):.4f} "
              f"p99 {np.percentile(a, 99):.4f} | signed mean {signed.mean():+.4f} (+ outside), "
              f"{(signed < 0).mean():.2f} of the points inside | completeness mean {c.mean():.4f} "
              f"median {np.median(c):.4f} (% of the diagonal)")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2:])
