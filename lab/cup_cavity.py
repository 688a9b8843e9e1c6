# SPDX-License-Identifier: Apache-2.0
"""What fills the ten-view cup's cavity in a fitted mesh, and which mesh surface the cavity's truth is scored against.

The suite's cup (``hard_scenes._mug_sdf``: a cylinder of radius 0.5, its cavity of radius 0.42 from z = 0.08
up through the open top) is seen by ten views, most of which do not see the cavity's lower wall and floor.
Completeness scores each truth point by its nearest mesh point, so the cavity's truth is scored against
whatever the mesh holds there: for each mesh this prints

* the whole truth's completeness and accuracy (% of the truth's diagonal, 200,000 area samples each);
* the cavity truth's (inner wall and floor) completeness, and the share of its points whose nearest mesh point
  is itself off the truth (farther than tau = 0.5 % of the diagonal: no part of the cup's surface);
* the same for the cavity's lower third (z < 0.3, the part ten views see least);
* the share of the mesh's area inside the cavity (strictly within it: r < 0.40, 0.10 < z < 0.98) and how
  much of that is off the truth.

First it prints how many of the scene's training views see the cavity's truth (``wtopo.metrics.view_counts``,
the suite's observed-region rule: two views fix a point). ``--section PNG`` draws each mesh's cut through the
cup's axis (the plane y = 0) over the truth's outline.

    PYTHONPATH=. .venv/bin/python lab/cup_cavity.py [--section cut.png] RUN/seed0/mug_sparse_default/mesh.ply ...
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from hard_scenes import mug_mesh  # noqa: E402

TAU = 0.5  # % of the diagonal, as the suite's F-score, floaters and holes
SAMPLES = 200_000
CAVITY_R, CAVITY_Z = 0.42, (0.08, 1.0)  # hard_scenes._mug_sdf's cavity


def _cavity_truth(p: np.ndarray) -> np.ndarray:
    r = np.hypot(p[:, 0], p[:, 1])
    return (r < CAVITY_R + 0.005) & (p[:, 2] > CAVITY_Z[0] - 0.005) & (p[:, 2] < CAVITY_Z[1] - 0.005)


def _inside_cavity(p: np.ndarray) -> np.ndarray:
    r = np.hypot(p[:, 0], p[:, 1])
    return (r < CAVITY_R - 0.02) & (p[:, 2] > CAVITY_Z[0] + 0.02) & (p[:, 2] < CAVITY_Z[1] - 0.02)


def measure(mesh: trimesh.Trimesh, truth_points: np.ndarray, diag: float) -> dict:
    """The figures the module docstring lists, for one mesh."""
    pm, _ = trimesh.sample.sample_surface(mesh, SAMPLES, seed=1)
    to_truth = cKDTree(truth_points).query(pm)[0] / diag * 100  # each mesh point's distance to the truth
    dt, nearest = cKDTree(pm).query(truth_points)
    dt = dt / diag * 100  # each truth point's distance to the mesh
    off = to_truth[nearest] > TAU  # the truth point's nearest mesh point is no part of the cup's surface
    cav = _cavity_truth(truth_points)
    low = cav & (truth_points[:, 2] < 0.3)
    inside = _inside_cavity(pm)
    return {"completeness": float(dt.mean()), "accuracy": float(to_truth.mean()),
            "cavity_completeness": float(dt[cav].mean()), "cavity_served_off_truth": float(off[cav].mean()),
            "low_completeness": float(dt[low].mean()), "low_served_off_truth": float(off[low].mean()),
            "mesh_in_cavity": float(inside.mean()),
            "mesh_in_cavity_off_truth": float((to_truth[inside] > TAU).mean()) if inside.any() else 0.0}


def cavity_views(truth: trimesh.Trimesh, truth_points: np.ndarray, diag: float) -> dict:
    """How many training views of the suite's ten-view cup see its cavity's truth: ``{k: share}`` for k = 0,
    1, 2 and more (the share of the cavity's samples seen by exactly k views, the last by k or more)."""
    from hard_scenes import SCENES
    from wtopo.metrics import view_counts

    scene = SCENES["mug_sparse"]()[0]
    idx = scene.train_indices if scene.train_indices is not None else range(len(scene.cameras))
    cav = truth_points[_cavity_truth(truth_points)]
    n = view_counts(cav, truth, [scene.cameras[i] for i in idx], tolerance=1e-3 * diag)
    return {0: float((n == 0).mean()), 1: float((n == 1).mean()), 2: float((n >= 2).mean())}


def section(meshes: list[tuple[str, trimesh.Trimesh]], out: str) -> None:
    """Each mesh's cut through the plane y = 0 (area samples within 0.015 of it) over the truth's outline;
    ``meshes``: (title, mesh) pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(meshes), figsize=(5 * len(meshes), 4.6), squeeze=False)
    for ax, (name, mesh) in zip(axes[0], meshes):
        p, _ = trimesh.sample.sample_surface(mesh, 400_000, seed=0)
        cut = np.abs(p[:, 1]) < 0.015
        ax.scatter(p[cut, 0], p[cut, 2], s=0.3)
        ax.plot([-0.5, -0.5, 0.5, 0.5], [1, 0, 0, 1], "r-", lw=0.6)
        ax.plot([-CAVITY_R, -CAVITY_R, CAVITY_R, CAVITY_R], [1, CAVITY_Z[0], CAVITY_Z[0], 1], "r-", lw=0.6)
        ax.set_title(name, fontsize=9)
        ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(out, dpi=80)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("meshes", nargs="+", help="fitted meshes of the ten-view cup (mesh.ply)")
    ap.add_argument("--section", help="PNG of each mesh's cut through the cup's axis")
    args = ap.parse_args(argv)
    paths = args.meshes
    truth = mug_mesh()
    diag = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
    pt, _ = trimesh.sample.sample_surface(truth, SAMPLES, seed=0)
    seen = cavity_views(truth, pt, diag)
    print(f"The cavity's truth ({100 * _cavity_truth(pt).mean():.0f} % of the truth's area) seen by no training "
          f"view: {100 * seen[0]:.0f} %, by one: {100 * seen[1]:.0f} %, by two or more: {100 * seen[2]:.0f} %")
    print("| mesh | completeness | accuracy | cavity completeness (served off the truth) | lower cavity "
          "(served off the truth) | mesh area in the cavity (off the truth) |")
    print("|---|---|---|---|---|---|")
    # each mesh named by its run folder and fit folder (seed0/mug_sparse_default)
    meshes = [(os.path.join(*os.path.normpath(p).split(os.sep)[-3:-1]), trimesh.load(p, process=False)) for p in paths]
    for name, mesh in meshes:
        m = measure(mesh, pt, diag)
        print(f"| {name} | {m['completeness']:.3f} | {m['accuracy']:.3f} | {m['cavity_completeness']:.3f} "
              f"({100 * m['cavity_served_off_truth']:.0f} %) | {m['low_completeness']:.3f} "
              f"({100 * m['low_served_off_truth']:.0f} %) | {100 * m['mesh_in_cavity']:.1f} % "
              f"({100 * m['mesh_in_cavity_off_truth']:.0f} %) |", flush=True)
    if args.section:
        section(meshes, args.section)


if __name__ == "__main__":
    main()
