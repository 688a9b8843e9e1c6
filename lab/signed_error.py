# SPDX-License-Identifier: Apache-2.0
"""Which side of the truth a mesh lies on (#59: why the authors' bunny64 mesh is closer than wtopo's).

    .venv/bin/python lab/signed_error.py TRUTH.ply MESH.ply [MESH.ply ...]

For each mesh: 300,000 points sampled on its surface, each one's offset from the plane of the nearest of
3,000,000 points sampled on the truth (that sample's face plane, + outside along its normal), as % of the truth's
bounding-box diagonal. The plane's offset, not the distance to the sample, so the samples' spacing (about 0.03 % of
the diagonal) does not add to it. A lab measurement: its means are not the scorer's accuracy
(benchmarks/peers/score.py). Nothing imports it.
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
        _, i = tree.query(pts)
        signed = np.einsum("ij,ij->i", pts - tp[i], tn[i]) / diag * 100.0
        a = np.abs(signed)
        print(f"{path}: |offset| mean {a.mean():.4f} median {np.median(a):.4f} p90 {np.percentile(a, 90):.4f} "
              f"p99 {np.percentile(a, 99):.4f} | signed mean {signed.mean():+.4f} median {np.median(signed):+.4f} "
              f"(+ outside), {(signed < 0).mean():.2f} of the points inside (% of the diagonal)")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2:])
