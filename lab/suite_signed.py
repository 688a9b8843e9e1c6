# SPDX-License-Identifier: Apache-2.0
"""Which side of the truth the hard suite's meshes lie on (#59; design/decisions.md, "Open: wtopo's meshes lie inside
the surface").

    .venv/bin/python lab/suite_signed.py RUN_DIR [RUN_DIR ...] [--scenes torus mug ...]

Each RUN_DIR is a lab/hard.py seed folder (``<run-dir>/<label>/seed0``) holding ``SCENE_default/mesh.ply``. For each
scene the truth is lab/hard.py's own (``_build``) and each mesh's signed offset is lab/signed_error.py's: the mean,
the median, the share inside and the mean unsigned offset, as % of the truth's diagonal. lab/silhouette_excess.py
uses its sample counts.
"""

import argparse
import os
import sys

import numpy as np
import trimesh

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard  # noqa: E402
from signed_error import TruthPlanes  # noqa: E402

SAMPLES = (2_000_000, 200_000)  # (truth, mesh)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--scenes", nargs="+", default=["torus", "mug", "chair", "chair_box", "bowl", "blob_flat"])
    a = ap.parse_args(argv)
    print("| scene | run | mean signed | median | inside | mean unsigned |")
    print("|---|---|---|---|---|---|")
    for name in a.scenes:
        planes = TruthPlanes(hard._build(name)[1], SAMPLES[0])  # one per scene, for every run's mesh
        for run in a.runs:
            path = os.path.join(run, f"{name}_default", "mesh.ply")
            if not os.path.exists(path):
                continue
            s = planes.offsets(trimesh.load(path, force="mesh"), SAMPLES[1])
            print(f"| {name} | {run} | {s.mean():+.4f} | {np.median(s):+.4f} | {(s < 0).mean() * 100:.0f} % "
                  f"| {np.abs(s).mean():.4f} |", flush=True)


if __name__ == "__main__":
    main()
