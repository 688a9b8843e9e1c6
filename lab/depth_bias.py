# SPDX-License-Identifier: Apache-2.0
"""Where the inward offset of wtopo's meshes starts (#59, lab/signed_error.py): a fit's rendered surfel depth
against the scene's true z-depth, on a built-in scene with ground-truth depth.

    .venv/bin/wtopo fit bunny --out RUN --set polish.iterations=0     # the surfels the final mesh came from
    .venv/bin/python lab/depth_bias.py RUN [SCENE]

On every training view's pixels inside the true mask where the render's opacity reaches 0.5 (the pixels the
final fusion takes): the median and the expected depth minus the true depth (+: behind the true surface), as %
of the true mesh's bounding-box diagonal, overall and by the angle between the true normal and the ray. Nothing
imports it.
"""

import json
import os
import sys

import numpy as np
import torch

from wtopo import fit, ops, scenes
from wtopo.cli import _apply_set
from wtopo.fitting.config import FitConfig
from wtopo.io.ply import read_surfels_ply


def fit_without_polish(out: str, args: list[str]) -> tuple[str, dict]:
    """``args``: ``[SCENE] [--set key=value ...]``. Fits SCENE (default bunny) on the CPU with no polish, so the
    surfels written to ``out`` are the ones the final mesh was fused from; returns the scene's name and the report.
    The lab scripts that change one mechanism before calling it (ncc_coverage.py, mask_warmup_only.py) share it."""
    name = args[0] if args and not args[0].startswith("--") else "bunny"
    cfg = FitConfig()
    for kv in ["polish.iterations=0", *(args[i + 1] for i, a in enumerate(args) if a == "--set")]:
        _apply_set(cfg, kv)
    return name, fit(scenes.load(name), cfg, out_dir=out, progress=False).report


def main(run: str, name: str = "bunny") -> None:
    scene = scenes.load(name)
    s = read_surfels_ply(os.path.join(run, "surfels.ply"))
    with open(os.path.join(run, "plan.json")) as f:
        sigma = float(json.load(f)["filter_sigma"]["value"])
    cfg = ops.RasterConfig(filter_sigma=sigma)
    lo, hi = scene.gt_mesh.bounds
    diag = float(np.linalg.norm(hi - lo))
    t = lambda a: torch.as_tensor(np.asarray(a))  # noqa: E731
    rows = {"median": [], "expected": []}
    cosines = []
    scene = scene.split("train")
    for i in range(len(scene.cameras)):
        cam = scene.cameras[i]
        out = ops.rasterize_surfels(t(s.means), t(s.quats), t(s.scales), t(s.opacities), t(s.sh), cam, config=cfg)
        gt = np.asarray(scene.depths[i])
        keep = (np.asarray(scene.masks[i]) > 0.5) & (out.alpha.numpy() >= 0.5) & (gt > 0)
        n = np.asarray(scene.normals[i])
        d = cam.pixel_rays()[1].numpy().reshape(n.shape)
        cosines.append(np.abs(np.sum(n * d, axis=-1) / np.maximum(np.linalg.norm(d, axis=-1), 1e-12))[keep])
        rows["median"].append((out.median_depth.numpy() - gt)[keep])
        rows["expected"].append((out.depth.numpy() - gt)[keep])
    c = np.concatenate(cosines)
    print(f"{len(c)} pixels, filter_sigma {sigma}")
    for k, v in rows.items():
        e = np.concatenate(v) / diag * 100
        parts = [f"{k}: mean {e.mean():+.4f} median {np.median(e):+.4f} (% of the diagonal; + behind)"]
        for a, b in [(0.0, 0.3), (0.3, 0.6), (0.6, 0.85), (0.85, 1.01)]:
            m = (c >= a) & (c < b)
            if m.any():
                parts.append(f"|cos| {a:.2f}-{b:.2f}: {e[m].mean():+.4f} ({m.mean():.2f} of the pixels)")
        print("\n  ".join(parts))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(*sys.argv[1:3])
