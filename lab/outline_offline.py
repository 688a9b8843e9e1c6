# SPDX-License-Identifier: Apache-2.0
"""The outline offset applied offline to a held-out fit's mesh (lab/hard.md "outline"): what the product's
``final.outline`` would have done to a mesh made without it.

    PYTHONPATH=. .venv/bin/python lab/outline_offline.py SCENE RUN_DIR

SCENE: a name of lab/heldout.py (its 32-view rig at 128 px is rebuilt); RUN_DIR: a fit of it made with
``--set final.outline=false`` (or before the outline existed), whose ``mesh.ply`` is in the scene's frame. Prints
the product's ``outline_offset`` record (wtopo.fitting._final_mesh._outline on the scene's training views, with
the run's thin-part decision from its report.json), then the mesh's Chamfer (% of the truth's diagonal, 200,000
samples) before and after. The fits are deterministic, so that mesh is the one the product moves. Nothing imports
it.
"""

import os
import sys

import torch
import trimesh

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ridge_outline import heldout_fit  # noqa: E402
from wtopo.fitting._final_mesh import _outline  # noqa: E402
from wtopo.metrics import chamfer  # noqa: E402


def main(name: str, run: str) -> None:
    gt, cameras, masks, thin, path = heldout_fit(name, run)
    mesh = trimesh.load(path, process=False)
    events = []
    moved = _outline(mesh, cameras, masks, record=lambda e, **k: events.append(k),
                     device=torch.device("cpu"), thin=thin)
    before = chamfer(mesh, gt, n_samples=200_000).chamfer_rel * 100
    after = chamfer(moved, gt, n_samples=200_000).chamfer_rel * 100
    change = 100 * (after / before - 1)
    print(f"{name} (thin {thin}): {events[0]}; Chamfer {before:.4f} -> {after:.4f} ({change:+.1f} %)")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(*sys.argv[1:3])
