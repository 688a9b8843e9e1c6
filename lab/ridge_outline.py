# SPDX-License-Identifier: Apache-2.0
"""The outline offset with and without its ridge test, applied offline to a fit's mesh from before the offset (#59,
lab/hard.md "outline on the chair"). Nothing imports it.

    PYTHONPATH=. .venv/bin/python lab/ridge_outline.py EXCH PRE_MESH [EXCH PRE_MESH ...]
    PYTHONPATH=. .venv/bin/python lab/ridge_outline.py --heldout NAME RUN_DIR [NAME RUN_DIR ...]

EXCH: an exchange folder of benchmarks/peers/export.py (training cameras, masks, ``gt.ply``); PRE_MESH: a fit's mesh
before the offset (lab/pre_outline.py), in that frame. ``--heldout``: a scene of lab/heldout.py (its 32-view rig at
128 px rebuilt) and a fit of it made with ``--set final.outline=false`` (its thin-part decision read from its
report.json). Per mesh: the product's ``_outline`` (wtopo/fitting/_final_mesh.py) as it is, and with every outline
pixel counted as a smooth limb (``RIDGE_SPREAD`` 2: the measure before the ridge test), each one's record and the
Chamfer after it (% of the truth's diagonal, 200,000 samples, seed 0, as benchmarks/peers/score.py).
"""

import json
import os
import sys
from unittest import mock

import numpy as np
import torch
import trimesh

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.join(HERE, "..", "benchmarks", "peers")]

from wtopo.fitting._final_mesh import _outline  # noqa: E402
from wtopo.geometry import outline  # noqa: E402
from wtopo.metrics import chamfer  # noqa: E402


def _exchange(root: str, path: str):
    import exchange

    ex = exchange.load(root)
    return ex.gt(), [ex.camera(i) for i in ex.train], [ex.mask(i) >= 0.5 for i in ex.train], False, path


def heldout_fit(name: str, run: str):
    """A held-out scene's truth, training cameras and masks, the fit's thin-part decision and its mesh's path."""
    import hard_scenes as hs
    import heldout
    from wtopo import scenes

    hs.MESH_CACHE[:] = [".hardcache"]
    sdf, lo, hi = heldout.SCENES[name]
    gt = hs.sdf_mesh(sdf, lo, hi, 0.006)
    sc = scenes.from_mesh(gt, n_views=32, resolution=128, rig="sphere", texture="coffee", background="black",
                          seed=7, up=(0, 0, 1), n_test=hs.N_TEST, name=name)
    train = sc.split("train")
    with open(os.path.join(run, "report.json")) as f:
        thin = not json.load(f).get("coevolution", {}).get("mesh_terms", True)
    return gt, train.cameras, list(train.masks), thin, os.path.join(run, "mesh.ply")


def _chamfer(mesh, gt) -> float:
    return 100 * chamfer(mesh, gt, n_samples=200_000, seed=0).chamfer_rel


def main(argv: list[str]) -> None:
    held = argv[:1] == ["--heldout"]
    args = argv[1:] if held else argv
    for a, b in zip(args[::2], args[1::2]):
        gt, cams, masks, thin, path = (heldout_fit if held else _exchange)(a, b)
        mesh = trimesh.load(path, process=False)

        row = [f"{os.path.basename(a.rstrip('/'))} (thin {thin}): before {_chamfer(mesh, gt):.4f}"]
        for label, spread in (("uniform", 2.0), ("ridge", outline.RIDGE_SPREAD)):
            events = []
            with mock.patch.object(outline, "RIDGE_SPREAD", spread):
                out = _outline(mesh, cams, masks, record=lambda e, ev=events, **k: ev.append(k),
                               device=torch.device("cpu"), thin=thin)
            ev = {k: v for k, v in events[0].items() if k in ("pixels", "views", "smooth_share", "distance", "skipped")}
            if "distance" in ev:
                ev["distance"] = float(np.round(ev["distance"], 6))
            row.append(f"{label} {_chamfer(out, gt):.4f} {ev}")
        print(" | ".join(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
