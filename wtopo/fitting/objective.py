# SPDX-License-Identifier: Apache-2.0
"""The objective of one iteration: which loss terms of :mod:`wtopo.fitting.losses` apply, with which
weight, on which pixels. A new term is one more entry in :meth:`Objective.__call__`'s dictionary.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import torch

from .config import FitConfig, stage_iteration
from .losses import mesh_depth_loss, mesh_normal_loss, scale_regularizer
from .multiview import MultiViewNCC
from .pixel_terms import ALPHA_COVERED, PixelTerms, TermSet, halo_ring
from .proxy import ProxyMesh, ProxyResult
from .stages import ROI_EXTENT, Renderer, Stage
from .surfels import Surfels

__all__ = ["Objective", "Terms", "LossLog"]

_DEPTH_EPS = 1e-4  # log-depth clamp, internal units (1e-4 of the unit cube)
_LOSS_EMA = 0.9  # smoothing of the loss shown on the progress bar
_DSSIM = 0.2  # weight of D-SSIM in the photometric term (1 - w) L1 + w (1 - SSIM): 3DGS's and 2DGS's value
_MAX_ANISOTROPY = 10.0  # ratio of the two surfel scales above which the scale regulariser acts (stops needles)
# the normal, distortion and multi-view terms start this fraction of the way through the warm-up
# (stage_iteration): on a blurry early state they would lock in its wrong geometry (2DGS starts them late)
_NORMAL_START = 0.5
_DISTORTION_START = 0.5
_MULTIVIEW_START = 0.5
# reference pixels drawn per iteration for the multi-view term (each a 7 x 7 window): 1/16 of the view, at most
# 4096 (1024 at 128 x 128 px; 4096 from 256 x 256 px up); design/decisions.md has the figures
_MULTIVIEW_FRACTION = 1.0 / 16.0
_MULTIVIEW_PIXELS = 4096


@dataclasses.dataclass
class Terms:
    """The loss terms of one iteration and what they were computed from.

    Attributes:
        losses: weighted terms by name, scalar tensors in the graph.
        render: the rasterizer output of the view.
        covered: pixels [H, W] bool whose opacity reaches :data:`ALPHA_COVERED`.
        proxy_built: the proxy mesh was built for the mesh terms this iteration.
        proxy: that proxy mesh (``None`` when it came out empty or was not built).
    """

    losses: dict[str, torch.Tensor]
    render: object
    covered: torch.Tensor
    proxy_built: bool = False
    proxy: ProxyResult | None = None


class Objective:
    """Computes the weighted loss terms of one training view.

    Args:
        cfg: configuration (``losses``, ``coevolution``).
        train: the training scene (internal frame): cameras, images, optional masks.
        render: the fit's renderer.
        mask_weight: the plan's mask-loss weight.
        warmup_end: first co-evolution iteration.
        timers: the fit's section timers (``"render"``, ``"losses"``, ``"proxy"``, ``"raycast"``).
        roi_center: [3] the region of interest's centre (internal frame): picks the neighbouring views
            of the multi-view term (``losses.multiview``); ``None`` leaves it out.
        mesh_every: the proxy is built and the mesh terms applied on every ``mesh_every``-th co-evolution
            iteration (counted from its first), weighted ``mesh_every`` (the preset's,
            :attr:`~wtopo.fitting.presets.Budget.mesh_every`).

    Attributes:
        mesh_terms: whether the co-evolution's mesh terms run at all (the fit sets it from
            :func:`~wtopo.fitting.thin_parts.thin_parts` at the co-evolution's start); ``True`` until then.
    """

    def __init__(self, cfg: FitConfig, train, *, render: Renderer, mask_weight: float, warmup_end: int, timers,
                 roi_center=None, mesh_every: int = 1):
        self.cfg = cfg
        lc = cfg.losses
        self.multiview = None
        if (lc.multiview or 0.0) > 0 and roi_center is not None and len(train.cameras) > 1:
            self.multiview = MultiViewNCC(train.cameras, train.images, roi_center, pixels=_MULTIVIEW_PIXELS,
                                          fraction=_MULTIVIEW_FRACTION, seed=cfg.runtime.seed)
        self.train = train
        self.render = render
        self.mask_weight = float(mask_weight)
        self.warmup_end = warmup_end
        self.timers = timers
        self.mesh_every = max(1, int(mesh_every))
        self.mesh_terms = True
        self.pixel_terms = PixelTerms()
        self.rings = None if train.masks is None else halo_ring(train.masks)  # [V, H, W]: each view's, once

    def __call__(self, stage: Stage, it: int, vi: int, surfels: Surfels, proxy: ProxyMesh, *,
                 defer_count: bool = False) -> Terms:
        """Render training view ``vi`` and compute its terms; in co-evolution build ``proxy`` from
        ``surfels`` (differentiably) for the mesh terms. ``defer_count``: see :class:`Renderer`
        (the caller checks ``terms.render.overflow``)."""
        lc, s, T = self.cfg.losses, surfels, self.timers
        cam = self.train.cameras[vi]
        img = self.train.images[vi]
        with T("render"):
            out = self.render(s, cam, defer_count=defer_count)
        L: dict[str, torch.Tensor] = {}
        with T("losses"):
            covered = out.alpha.detach() >= ALPHA_COVERED
            late = stage != Stage.WARMUP
            # the polish (before the final mesh) fits the photographs alone: no geometric regulariser either
            geometric = stage != Stage.POLISH
            masked = self.train.masks is not None and self.mask_weight > 0
            normal_on = geometric and (late or it >= stage_iteration(_NORMAL_START, self.warmup_end))
            dist_on = geometric and (late or it >= stage_iteration(_DISTORTION_START, self.warmup_end))
            mv = self.multiview
            mv_on = (geometric and mv is not None and mv.has_neighbours(vi)
                     and (late or it >= stage_iteration(_MULTIVIEW_START, self.warmup_end)))
            windows = mv.draw(it, vi, out.alpha.device) if mv_on else None
            mv_terms = {} if windows is None else {"multiview": lc.multiview, "sources": len(windows.images),
                                                   "half": windows.half}
            ts = TermSet(_DSSIM, mask=self.mask_weight if masked else 0.0, normal=lc.normal if normal_on else 0.0,
                         distortion=lc.distortion if dist_on else 0.0, **mv_terms)
            masks = self.train.masks
            values = self.pixel_terms(ts, out, img, None if masks is None else masks[vi],
                                      cam.pixel_rays(out.alpha.device) if ts.normal > 0 else None, windows,
                                      None if masks is None else self.rings[vi])
            L.update(zip(ts.names, values.unbind()))
            if mv_on and windows is None:  # a view too small for a window: the term is there, and zero
                L["multiview"] = out.median_depth.sum() * 0.0
            if lc.scale > 0:
                L["scale"] = lc.scale * scale_regularizer(s.scales, _MAX_ANISOTROPY)
        terms = Terms(L, out, covered)
        co = self.cfg.coevolution
        k = self.mesh_every
        if (stage == Stage.COEVOLUTION and co.enabled and self.mesh_terms and (lc.mesh_depth > 0 or lc.mesh_normal > 0)
                and (it - self.warmup_end) % k == 0):
            with T("proxy"):
                pm = proxy.build(s)
            terms.proxy_built, terms.proxy = True, pm
            if pm is not None:
                with T("raycast"):
                    mr = proxy.render(pm, cam)
                with T("losses"):
                    both = mr.mask & covered
                    if lc.mesh_depth > 0:
                        form = str(getattr(lc.depth_form, "value", lc.depth_form))
                        L["mesh_depth"] = k * lc.mesh_depth * mesh_depth_loss(out.median_depth, mr.depth, both,
                                                                          eps=_DEPTH_EPS, form=form, extent=ROI_EXTENT,
                                                                          debias=lc.mesh_depth_debias)
                    if lc.mesh_normal > 0:
                        L["mesh_normal"] = k * lc.mesh_normal * mesh_normal_loss(out.normal, mr.normal, both)
        return terms


class LossLog:
    """Sums of the loss terms since the last evaluation and a running average for the progress bar.

    Attributes:
        sums: per-term sums (and ``"total"``) since the last :meth:`take`.
        count: steps summed.
        ema: running average of the total loss.
    """

    def __init__(self):
        self.sums: dict[str, float] = defaultdict(float)
        self.count = 0
        self.ema = 0.0

    def add(self, terms: dict[str, float], *, first: bool) -> None:
        """Add one finite step's terms; ``first``: the first step of the fit (starts the average)."""
        total = sum(terms.values())
        for k, v in terms.items():
            self.sums[k] += v
        self.sums["total"] += total
        self.ema = total if first else _LOSS_EMA * self.ema + (1 - _LOSS_EMA) * total
        self.count += 1

    def take(self) -> dict[str, float]:
        """Mean of each term since the last call; clears the sums."""
        n = max(1, self.count)
        means = {k: v / n for k, v in self.sums.items()}
        self.sums.clear()
        self.count = 0
        return means
