# SPDX-License-Identifier: Apache-2.0
"""History records: losses, timings, and, with a ground-truth mesh, Chamfer / F-score / PSNR."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from .. import metrics

__all__ = ["geometry_metrics", "F_SCORE_TAU", "EVAL_SAMPLES"]

F_SCORE_TAU = 0.005
"""F-score threshold as a fraction of the ground truth's bounding-box diagonal."""
EVAL_SAMPLES = 20000
"""Surface samples per mesh for the Chamfer / F-score at evaluations during the fit."""


def geometry_metrics(mesh: trimesh.Trimesh | tuple, gt: trimesh.Trimesh, *, n_samples: int = EVAL_SAMPLES,
                     seed: int = 0) -> dict[str, float]:
    """Chamfer (absolute and relative to the gt diagonal), accuracy, completeness and F-score."""
    if isinstance(mesh, tuple):
        v, f = mesh
        mesh = trimesh.Trimesh(v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v,
                               f.detach().cpu().numpy() if isinstance(f, torch.Tensor) else f, process=False)
    if len(mesh.faces) == 0:
        return {}
    ch = metrics.chamfer(mesh, gt, n_samples=n_samples, seed=seed)
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    fs = metrics.f_score(mesh, gt, F_SCORE_TAU * diag, n_samples=n_samples, seed=seed)
    return {"chamfer": ch.chamfer, "chamfer_rel": ch.chamfer_rel, "accuracy_rel": ch.accuracy_rel,
            "completeness_rel": ch.completeness_rel, "f_score": fs.f_score, "precision": fs.precision,
            "recall": fs.recall}
