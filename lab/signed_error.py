# SPDX-License-Identifier: Apache-2.0
"""Which side of the truth a mesh lies on (#59: why the authors' bunny64 mesh is closer than wtopo's).

    .venv/bin/python lab/signed_error.py TRUTH.ply MESH.ply [MESH.ply ...]

For each mesh: 300,000 points sampled on its surface, each one's offset from the plane of the nearest of
3,000,000 points sampled on the truth (that sample's face plane, + outside along its normal), as % of the truth's
bounding-box diagonal. The plane's offset, not the distance to the sample, so the samples' spacing (about 0.03 % of
the diagonal) does not add to it. A lab measurement: its means are not the scorer's accuracy
(benchmarks/peers/score.py). lab/suite_signed.py and lab/silhouette_excess.py use its ``TruthPlanes``.
"""

import sys

import numpy as np
import trimesh
from scipy.spatial import cKDTree


class TruthPlanes:
    """Samples of the truth's surface with their face planes, built once per truth and queried for each mesh."""

    def __init__(self, truth: trimesh.Trimesh, samples: int = 3_000_000):
        self.diag = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
        self.points, faces = trimesh.sample.sample_surface(truth, samples, seed=1)
        self.normals = truth.face_normals[faces]
        self.tree = cKDTree(self.points)

    def offsets(self, mesh: trimesh.Trimesh, samples: int = 300_000) -> np.ndarray:
        """Each mesh sample's offset from the plane of its nearest truth sample [% of the diagonal, + outside]."""
        pts, _ = trimesh.sample.sample_surface(mesh, samples, seed=0)
        _, i = self.tree.query(pts)
        return np.einsum("ij,ij->i", pts - self.points[i], self.normals[i]) / self.diag * 100.0


def main(truth_path: str, mesh_paths: list[str]) -> None:
    planes = TruthPlanes(trimesh.load(truth_path, force="mesh"))
    for path in mesh_paths:
        signed = planes.offsets(trimesh.load(path, force="mesh"))
        a = np.abs(signed)
        print(f"{path}: |offset| mean {a.mean():.4f} median {np.median(a):.4f} p90 {np.percentile(a, 90):.4f} "
              f"p99 {np.percentile(a, 99):.4f} | signed mean {signed.mean():+.4f} median {np.median(signed):+.4f} "
              f"(+ outside), {(signed < 0).mean():.2f} of the points inside (% of the diagonal)")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2:])
