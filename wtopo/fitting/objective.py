# SPDX-License-Identifier: Apache-2.0
"""The objective of one iteration: which loss terms of :mod:`wtopo.fitting.losses` apply, with which
weight, on which pixels. A new term is one more entry in :meth:`Objective.__call__`'s dictionary.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from collections.abc import Callable

import torch

from .config import FitConfig, RenderedDepth, stage_iteration
from .geometric import ForwardBackwardDepth
from .losses import (
    boundary_band,
    depth_normals,
    distortion,
    erode,
    halo_target,
    mask_loss,
    mesh_depth_loss,
    mesh_normal_loss,
    normal_consistency,
    photometric,
    scale_regularizer,
)
from .multiview import MultiViewNCC
from .proxy import ProxyMesh, ProxyResult
from .stages import ROI_EXTENT, Renderer, Stage
from .surfels import Surfels
from .view_support import ViewSupport

__all__ = ["Objective", "Terms", "LossLog"]

ALPHA_COVERED = 0.5
"""A pixel is covered by the surfels when their rendered opacity reaches this."""
_DEPTH_EPS = 1e-4  # log-depth clamp, internal units (1e-4 of the unit cube)
_LOSS_EMA = 0.9  # smoothing of the loss shown on the progress bar
_DSSIM = 0.2  # weight of D-SSIM in the photometric term (1 - w) L1 + w (1 - SSIM): 3DGS's and 2DGS's value
_HALO_RING = 0.01  # outside the mask, a halo target above this leaves the pixel out of the photometric term
_MAX_ANISOTROPY = 10.0  # ratio of the two surfel scales above which the scale regulariser acts (stops needles)
_PHOTO_GATE_MARGIN = 0.1  # 1 - NCC by which the photographs must prefer the surfels' depth (losses.mesh_photo_gate)
_SUPPORT_CELLS = 2.0  # proxy cells of depth within which another view sees the surfels' point (mesh_view_support)


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
            of the multi-view terms (``losses.multiview``, ``losses.multiview_geometric``); ``None``
            leaves them out.

    Attributes:
        mesh_terms: whether the co-evolution's mesh terms run at all (the fit sets it from
            :func:`~wtopo.fitting.thin_parts.thin_parts` at the co-evolution's start); ``True`` until then.
    """

    def __init__(self, cfg: FitConfig, train, *, render: Renderer, mask_weight: float, warmup_end: int, timers,
                 roi_center=None):
        self.cfg = cfg
        lc = cfg.losses
        self.multiview = None
        if (lc.multiview or 0.0) > 0 and roi_center is not None and len(train.cameras) > 1:
            self.multiview = MultiViewNCC(train.cameras, train.images, roi_center, pixels=lc.multiview_pixels,
                                          seed=cfg.runtime.seed)
        # the mesh terms' photo-consistency gate scores windows as the multi-view term does (shared when on)
        self.photo_gate = None
        if lc.mesh_photo_gate > 0 and roi_center is not None and len(train.cameras) > 1:
            self.photo_gate = self.multiview or MultiViewNCC(train.cameras, train.images, roi_center,
                                                             seed=cfg.runtime.seed)
        self.geometric = None
        if lc.multiview_geometric > 0 and roi_center is not None and len(train.cameras) > 1:
            self.geometric = ForwardBackwardDepth(train.cameras, roi_center, pixels=lc.multiview_pixels,
                                                  seed=cfg.runtime.seed)
        self.view_support = None  # the mesh terms' two-view support (losses.mesh_view_support)
        if lc.mesh_view_support >= 2 and roi_center is not None and len(train.cameras) > 1:
            self.view_support = ViewSupport(train.cameras, min_views=lc.mesh_view_support, center=roi_center)
        self.train = train
        self.render = render
        self.mask_weight = float(mask_weight)
        self.warmup_end = warmup_end
        self.timers = timers
        self.mesh_terms = True
        self._bands: dict[int, torch.Tensor] = {}  # training view -> silhouette band (masks are fixed)
        self._halos: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}  # view -> (mask target, halo ring)

    def _band(self, vi: int) -> torch.Tensor | None:
        lc = self.cfg.losses
        if self.train.masks is None or lc.silhouette_band <= 0:
            return None
        band = self._bands.get(vi)
        if band is None:
            band = self._bands[vi] = boundary_band(self.train.masks[vi], lc.silhouette_band)
        return band

    def _halo(self, vi: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(target opacity [H, W], ring [H, W] bool)`` of view ``vi`` with ``losses.mask_halo``: the
        mask term's target and the pixels outside the mask the target lets the low-pass cover."""
        if self.train.masks is None or not self.cfg.losses.mask_halo:
            return None
        h = self._halos.get(vi)
        if h is None:
            m = self.train.masks[vi]
            t = halo_target(m, self.cfg.filter_sigma)
            h = self._halos[vi] = (t, (t > _HALO_RING) & ~m)
        return h

    def _depth_alpha(self, surfels: Surfels, vi: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Training view ``vi``'s rendered median z-depth and opacity [H, W], without gradient."""
        with torch.no_grad():
            o = self.render(surfels, self.train.cameras[vi])
        return o.median_depth, o.alpha

    def retry_point(self, proxy: ProxyMesh) -> Callable[[], None]:
        """What a call changes besides its result, captured now: the returned function puts it back, so
        the same step computed again (the fit's render after a binning overflow) counts once. That is
        ``proxy``'s silhouette offset (a running estimate a call folds one view into) and the view
        support's counts; the multi-view terms draw their pixels from a seed per iteration already."""
        sil = proxy.silhouette
        offset = None if sil is None else sil.value
        vs = self.view_support
        counts = None if vs is None else vs.counts_state()

        def undo() -> None:
            if sil is not None:
                sil.value = offset
            if vs is not None:
                vs.restore_counts(counts)

        return undo

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
            band = self._band(vi)
            halo = self._halo(vi)
            skip = band  # pixels left out of the photometric term: the band and the halo's ring
            if halo is not None:
                skip = halo[1] if skip is None else skip | halo[1]
            # the band is left out by rendering the target there: zero loss, zero gradient
            rgb = out.rgb if skip is None else torch.where(skip[..., None], img, out.rgb)
            L["photo"] = photometric(rgb, img, _DSSIM)
            covered = out.alpha.detach() >= ALPHA_COVERED
            if self.train.masks is not None and self.mask_weight > 0:
                m = self.train.masks[vi]
                target = m.to(out.alpha.dtype) if halo is None else halo[0].to(out.alpha.dtype)
                a = out.alpha if band is None else torch.where(band, target, out.alpha)
                L["mask"] = self.mask_weight * mask_loss(a, target)
            late = stage != Stage.WARMUP
            if lc.normal > 0 and (late or it >= stage_iteration(lc.normal_start_fraction, self.warmup_end)):
                o, d = cam.pixel_rays(out.alpha.device)
                dn, dmask = depth_normals(out.median_depth, o, d, covered)
                L["normal"] = lc.normal * normal_consistency(out.normal, dn, out.alpha, dmask)
            if lc.distortion > 0 and (late or it >= stage_iteration(lc.distortion_start_fraction, self.warmup_end)):
                L["distortion"] = lc.distortion * distortion(out.distortion)
            mv, gm = self.multiview, self.geometric
            mv_on = late or it >= stage_iteration(lc.multiview_start_fraction, self.warmup_end)
            if mv is not None and mv_on and mv.has_neighbours(vi):
                L["multiview"] = lc.multiview * mv(it, vi, out.median_depth, out.normal, out.alpha)
            if gm is not None and mv_on and gm.has_neighbours(vi):
                nj = gm.neighbour(it, vi)
                with T("render_neighbour"), torch.no_grad():  # the neighbour's depth is the target
                    on = self.render(s, self.train.cameras[nj])
                L["geometric"] = lc.multiview_geometric * gm(it, vi, out.median_depth, out.alpha, nj,
                                                             on.median_depth, on.alpha)
            if lc.scale > 0:
                L["scale"] = lc.scale * scale_regularizer(s.scales, _MAX_ANISOTROPY)
        terms = Terms(L, out, covered)
        co = self.cfg.coevolution
        n_co = int(co.iterations or 0)
        mesh_on = self.mesh_terms and (self.warmup_end + stage_iteration(lc.mesh_start_fraction, n_co) <= it
                   < self.warmup_end + stage_iteration(lc.mesh_end_fraction, n_co))
        if stage == Stage.COEVOLUTION and co.enabled and mesh_on and (lc.mesh_depth > 0 or lc.mesh_normal > 0):
            with T("proxy"):
                pm = proxy.build(s)
            terms.proxy_built, terms.proxy = True, pm
            if pm is not None:
                with T("raycast"):
                    mr = proxy.render(pm, cam)
                if proxy.silhouette is not None and self.train.masks is not None:
                    with torch.no_grad():  # the proxy's silhouette against the mask: its offset for the next builds
                        proxy.silhouette.update(mr.mask, mr.depth, self.train.masks[vi], float(cam.K[0, 0]))
                with T("losses"):
                    both = mr.mask & covered
                    supported = proxy.supported_pixels(pm, mr, s)
                    if supported is not None:  # pixels that see surface no surfel backs carry no mesh term
                        both = both & supported
                    vs = self.view_support
                    if vs is not None:  # pixels whose surfel point too few views see carry no mesh term
                        with T("view_support"), torch.no_grad():
                            vs.remember(vi, out.median_depth, out.alpha)
                            both = both & vs.supported(vi, out.median_depth, both, _SUPPORT_CELLS * proxy.cell,
                                                       render=lambda u: self._depth_alpha(s, u))
                    if lc.mesh_inset > 0:  # parts narrower than 2 inset + 1 pixels carry no mesh term
                        both = erode(both, lc.mesh_inset)
                    if self.photo_gate is not None and self.photo_gate.has_neighbours(vi):
                        # pixels where the surfels and the proxy disagree by more than mesh_photo_gate proxy
                        # cells and the photographs prefer the surfels' depth carry no mesh term
                        with T("photo_gate"), torch.no_grad():
                            ds, dm, n = out.median_depth, mr.depth, out.normal  # one normal: only depth compared
                            far = both & ((ds - dm).abs() > lc.mesh_photo_gate * proxy.cell)
                            both = both & ~self.photo_gate.prefers(it, vi, ds, n, dm, n, far, _PHOTO_GATE_MARGIN)
                    if lc.mesh_depth > 0:
                        sd = out.median_depth if lc.mesh_depth_source == RenderedDepth.MEDIAN else out.depth
                        form = str(getattr(lc.depth_form, "value", lc.depth_form))
                        L["mesh_depth"] = lc.mesh_depth * mesh_depth_loss(sd, mr.depth, both, eps=_DEPTH_EPS, form=form,
                                                                          extent=ROI_EXTENT,
                                                                          debias=lc.mesh_depth_debias,
                                                                          robust=(lc.mesh_depth_robust * proxy.cell
                                                                                  if lc.mesh_depth_robust > 0 else 0.0),
                                                                          robust_behind=lc.mesh_depth_robust_behind,
                                                                          behind=lc.mesh_depth_behind)
                    if lc.mesh_normal > 0:
                        L["mesh_normal"] = lc.mesh_normal * mesh_normal_loss(out.normal, mr.normal, both)
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
