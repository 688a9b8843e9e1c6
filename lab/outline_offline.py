# SPDX-License-Identifier: Apache-2.0
"""The outline offset applied offline to a held-out fit's mesh (lab/hard.md "outline"): what the product's
``final.outline`` would have done to a mesh made without it.

    PYTHONPATH=. .venv/bin/python lab/outline_offline.py SCENE RUN_DIR

SCENE: a name of lab/heldout.py (its 32-view rig at 128 px is rebuilt); RUN_DIR: a fit of it made with
``--set final.outline=false`` (or before the outline existed), whose ``mesh.ply`` is in the scene's frame. Prints
the median offset in pixels (and the views' 10th-90th percentiles), then the mesh's Chamfer (% of the truth's
diagonal, 200,000 samples) before and after moving it by the offset, capped at one footprint as the product does.
The fits are deterministic, so that mesh is the one the product moves. The product's thin rule (an object whose
mesh terms were off only moves inward) is not applied here: the run's report says whether it holds. Nothing imports
it.
"""

import os
import sys

import numpy as np
import trimesh

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard_scenes as hs  # noqa: E402
import heldout  # noqa: E402
from wtopo import scenes  # noqa: E402
from wtopo.geometry.outline import offset_along_normals, outline_offset  # noqa: E402
from wtopo.metrics import chamfer  # noqa: E402


def main(name: str, run: str) -> None:
    hs.MESH_CACHE[:] = [".hardcache"]
    sdf, lo, hi = heldout.SCENES[name]
    gt = hs.sdf_mesh(sdf, lo, hi, 0.006)
    sc = scenes.from_mesh(gt, n_views=32, resolution=128, rig="sphere", texture="coffee", background="black",
                          seed=7, up=(0, 0, 1), n_test=hs.N_TEST, name=name)
    train = sc.split("train")
    mesh = trimesh.load(os.path.join(run, "mesh.ply"), process=False)
    off = outline_offset(mesh.vertices, mesh.faces, train.cameras, list(train.masks))
    px = off.median_pixels
    moved = off.distance * min(1.0, 1.0 / max(abs(px), 1e-12))
    before = chamfer(mesh, gt, n_samples=200_000).chamfer_rel * 100
    after = chamfer(offset_along_normals(mesh, moved), gt, n_samples=200_000).chamfer_rel * 100
    p10, p90 = np.percentile(off.pixels, [10, 90])
    print(f"{name}: {px:+.3f} px (views 10-90 % {p10:+.3f}..{p90:+.3f}); Chamfer {before:.4f} -> moved {after:.4f} "
          f"({100 * (after / before - 1):+.1f} %)")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(*sys.argv[1:3])
