# SPDX-License-Identifier: Apache-2.0
"""History records: losses, timings, and, with a ground-truth mesh, Chamfer / F-score / PSNR."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from .. import metrics

__all__ = ["geometry_metrics", "Evaluator", "F_SCORE_TAU", "EVAL_SAMPLES"]

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


_SSIM_WINDOW = 11  # the standard Gaussian SSIM window (Wang et al. 2004); smaller images get no SSIM


class Evaluator:
    """Held-out PSNR / SSIM (every scene) and, against a ground-truth mesh, Chamfer / F-score of a running fit.

    Args:
        test: the held-out scene (internal frame): cameras and images.
        gt: the ground-truth mesh (internal frame), or ``None``.
        render: the fit's renderer, ``render(surfels, camera)``.
        enabled: the plan's ``gt_metrics`` decision (geometry is measured only then).
        images: measure PSNR / SSIM of the held-out views (``runtime.eval_metrics``).
        held_out: whether ``test`` is really held out (else it is a subset of the training views,
            reported as ``image_metrics_on = "training"``).
        seed: surface-sampling seed of the geometry metrics.
    """

    def __init__(self, test, gt: trimesh.Trimesh | None, *, render, enabled: bool, seed: int, images: bool = True,
                 held_out: bool = True):
        self.test = test
        self.images = bool(images)
        self.held_out = bool(held_out)
        self.gt = gt
        self.render = render
        self.enabled = bool(enabled)
        self.seed = seed

    def image_metrics(self, surfels) -> dict[str, float]:
        """Mean PSNR [dB] and SSIM of ``surfels`` rendered in the held-out views.

        Masked captures are scored inside the masks (the IDR / NeuS convention: PSNR over the mask's
        pixels, SSIM of both images composited on black), so the figure measures the object, not the
        background it was photographed on; ``psnr_on`` says which (``"masks"`` or ``"image"``).
        """
        masks = getattr(self.test, "masks", None)
        p, s = [], []
        with torch.no_grad():
            for k, (cam, img) in enumerate(zip(self.test.cameras, self.test.images)):
                rgb = self.render(surfels, cam).rgb.clamp(0, 1)
                img = img.to(rgb.device)
                if masks is not None:
                    m = masks[k].to(rgb.device).bool()
                    p.append(float(metrics.psnr(rgb, img, mask=m)))
                    rgb, img = rgb * m[..., None], img * m[..., None]
                else:
                    p.append(float(metrics.psnr(rgb, img)))
                if min(rgb.shape[0], rgb.shape[1]) >= _SSIM_WINDOW:
                    s.append(float(metrics.ssim(rgb, img, window=_SSIM_WINDOW)))
        if not s:  # images smaller than the SSIM window
            s = [float("nan")]
        return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s)),
                "psnr_on": "masks" if masks is not None else "image",
                "image_metrics_on": "held_out" if self.held_out else "training"}

    def __call__(self, surfels, *, mesh: trimesh.Trimesh | None = None, proxy=None) -> dict[str, float]:
        """``psnr`` / ``ssim`` (inside the masks for masked captures) and, of ``mesh`` or else of the
        proxy mesh (:class:`~wtopo.fitting.proxy.ProxyResult`), both internal frame, ``chamfer``,
        ``f_score``, ``accuracy``, ``completeness`` (relative to the gt diagonal); empty when disabled."""
        rec = self.image_metrics(surfels) if self.images and len(self.test.cameras) else {}
        if not self.enabled:
            return rec
        if mesh is None and proxy is not None:
            mesh = (proxy.verts.detach().cpu(), proxy.faces.cpu())
        if mesh is not None:
            g = geometry_metrics(mesh, self.gt, seed=self.seed)
            if g:
                rec.update({"chamfer": g["chamfer_rel"], "f_score": g["f_score"], "accuracy": g["accuracy_rel"],
                            "completeness": g["completeness_rel"]})
        return rec
