# SPDX-License-Identifier: Apache-2.0
r"""Where the co-evolution's first geometry-aware spawns land on a suite scene, against its truth.

Starts the default configuration from a ``hard.py --paired`` warm-up (``runtime.start_from``), stops one
iteration into the co-evolution (after the TSDF re-initialisation and the first mesh guidance), and
compares the surfels spawned there (the last ``spawned`` of the checkpoint: spawns are appended) with the
others: distance to the truth's surface in % of its diagonal, the share farther than 0.5 % (the suite's
tau), the part of those on the outside of the solid, and the median opacity.

    PYTHONPATH=. .venv/bin/python lab/spawn_sites.py --scene mug_sparse --seed 0 \
        --warmup runs/abl/cpu_paired_cup_s0/seed0/mug_sparse_warmup --out /tmp/spawn_s0
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard  # noqa: E402
from hard_scenes import MESH_CACHE  # noqa: E402
from wtopo.fitting import fit  # noqa: E402
from wtopo.fitting.checkpoint import load_checkpoint  # noqa: E402

TAU = 0.5  # % of the truth's diagonal


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="mug_sparse")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--warmup", required=True, help="the warm-up folder of hard.py --paired")
    ap.add_argument("--out", required=True, help="the short fit's folder (replaced)")
    ap.add_argument("--mesh-cache", default=".hardcache")
    args = ap.parse_args(argv)
    MESH_CACHE[:] = [args.mesh_cache]
    scene, gt, _ = hard._build(args.scene)
    cfg = hard._config("default", [f"runtime.seed={args.seed}"])
    cfg.runtime.start_from = args.warmup
    shutil.rmtree(args.out, ignore_errors=True)
    cfg.runtime.stop_at = int(load_checkpoint(os.path.join(args.warmup, "checkpoints"))["iteration"]) + 1
    fit(scene, cfg, out_dir=args.out, progress=False)
    st = load_checkpoint(os.path.join(args.out, "checkpoints"))
    guidance = [e for e in st["events"] if e["event"] == "mesh_guidance"]
    print(f"iteration {st['iteration']}: {guidance}")
    spawned = int(guidance[0].get("spawned", 0)) if guidance else 0
    p = st["surfels"]["params"]
    pts = np.asarray(scene.normalization().to_world(p["means"].double().numpy()))
    opacity = torch.sigmoid(p["opacity_logits"]).reshape(-1).numpy()
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    samples, fi = trimesh.sample.sample_surface(gt, 400_000, seed=0)
    d, j = cKDTree(samples).query(pts)
    d = 100 * d / diag
    outside = np.einsum("ij,ij->i", pts - samples[j], gt.face_normals[fi][j]) > 0
    new = np.zeros(len(pts), bool)  # spawns are appended: the last ``spawned`` surfels
    if spawned:
        new[-spawned:] = True
    for name, m in (("the others", ~new), ("spawned", new)):
        if not m.any():
            continue
        far = d[m] > TAU
        print(f"{name}: {m.sum()} surfels, distance median {np.median(d[m]):.3f} % (90th percentile "
              f"{np.percentile(d[m], 90):.3f} %), farther than {TAU} %: {100 * far.mean():.1f} % (outside the "
              f"solid: {100 * np.mean(far & outside[m]):.1f} %), opacity median {np.median(opacity[m]):.2f}")


if __name__ == "__main__":
    main()
