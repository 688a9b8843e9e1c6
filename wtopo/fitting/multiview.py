# SPDX-License-Identifier: Apache-2.0
"""Multi-view photometric consistency of the rendered geometry (PGSR's patch NCC term).

The photometric loss compares each training view only with its own rendering, so a surface can
sit anywhere along the rays as long as its colours reproduce the photo: a textured ground seen at
a grazing angle, a weakly textured wall, a sparsely seen object come back at the wrong depth with
the right picture. Neighbouring photographs disagree with such a surface. For sampled pixels of
the reference view this term takes the rendered plane there (median depth and rendered normal),
maps a ``patch x patch`` window of reference pixels through that plane into neighbouring views
(the plane-induced homography, evaluated per pixel with the cameras' own rays and projection, so
distortion and skew need no undistortion), and scores the window's normalised cross-correlation
(NCC) against the neighbours' photographs. The loss is ``1 - NCC``; a gradient moves the depth and
the normal of the surfels the reference view's pixels rest on.

* Neighbours: :func:`wtopo.geometry.mvs.select_neighbours` (good triangulation angle at the region
  of interest's centre, optical axes within 75 degrees); two are drawn per iteration, each window
  keeps the better of the two costs (an occluded neighbour does not vote).
* Windows whose best cost reaches ``_MAX_COST`` (no neighbour correlates: occlusion, a view that
  does not see the point, a wildly wrong plane) and windows without texture (grey-level standard
  deviation under ``_MIN_STD``) carry no loss, as in PGSR (its ``ncc < 0.9`` mask).
* Pixels are drawn uniformly in the image interior on the fit's device (a generator there, seeded
  per iteration: no host-to-device copy, no host read); pixels the surfels do not cover (opacity
  under one half) are weighted out. How many: ``pixels``, or with ``fraction`` that fraction of the
  view's pixels up to ``pixels`` (the fit draws 1/16 of a view, at most 4,096: 1,024 windows at
  128 x 128 px, 4,096 from 256 x 256 px up; design/decisions.md).
* What depends only on the view is made once per view and device: its grey image and, per pixel, the
  mean and variance of the grey levels of the window centred there and the length of its ray.
  Every ray of a view starts at its centre (:meth:`wtopo.Camera.pixel_rays`), so a window's points
  on the plane are the centre plus its rays scaled by one ratio per pixel.

The windows are scored by :func:`wtopo.multiview_ncc.window_ncc_costs` (one Warp kernel forward, one
backward, on the fit's device; the torch formulation it replaced is ``tests/reference/multiview.py``'s
``plane_costs_torch``); only the rendered depth and normal carry gradients.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from ..camera import Camera
from ..geometry.mvs import TorchCams, gray, select_neighbours
from ..multiview_ncc import ReferenceWindows, source_params, window_ncc_costs

__all__ = ["MultiViewNCC", "Windows", "ncc_loss"]

_MAX_COST = 0.9  # windows whose best 1 - NCC reaches this carry no loss (PGSR: ncc < 0.9)
_MIN_STD = 0.01  # reference windows with a grey-level std below this (of [0, 1]) carry no loss
_NCC_EPS = 1e-6
_DRAWN_NEIGHBOURS = 2  # neighbours scored per iteration; each window keeps its better one
_GRAZING = 0.05  # |cos| between a patch ray and the plane normal below which the window is dropped
_ALPHA_COVERED = 0.5  # windows whose centre the surfels cover less than this carry no loss


class Windows(NamedTuple):
    """What one call of the term scores (drawn by :meth:`MultiViewNCC.draw`, on the fit's device).

    Attributes:
        py: window centre rows ``[P]`` int64.
        px: window centre columns ``[P]`` int64.
        reference: the reference view's :class:`~wtopo.multiview_ncc.ReferenceWindows`.
        images: the drawn neighbours' grey images, one or two ``[Hs, Ws]``.
        params: their rows seen from the reference view ``[len(images), 23]``.
        half: half the window side [pixels].
    """

    py: torch.Tensor
    px: torch.Tensor
    reference: ReferenceWindows
    images: tuple
    params: torch.Tensor
    half: int


def ncc_loss(depth: torch.Tensor, normal: torch.Tensor, alpha: torch.Tensor, w: Windows) -> torch.Tensor:
    """The term's value for the windows ``w`` of a rendered view: the mean best ``1 - NCC`` of the windows that
    count and correlate (a scalar; 0 when none does), differentiable in ``depth`` [H, W] and ``normal``
    [H, W, 3]; ``alpha`` [H, W] by value. No host synchronisation (the fit replays it in a CUDA graph)."""
    best, ok = _window_costs(depth, normal, alpha, w)
    keep = ok * (best.detach() < _MAX_COST)
    return (best * keep).sum() / keep.sum().clamp_min(1.0)


def _window_costs(depth, normal, alpha, w: Windows) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`window_ncc_costs` of the windows ``w`` with the term's thresholds: ``(cost [P], ok [P])``."""
    return window_ncc_costs(depth, normal, alpha, w.py, w.px, w.reference, w.images, w.params, half=w.half,
                            min_std=_MIN_STD, grazing=_GRAZING, alpha_min=_ALPHA_COVERED, eps=_NCC_EPS)


class MultiViewNCC:
    """The multi-view patch NCC term for training views.

    Args:
        cameras: training cameras (internal frame), at the resolution of ``images``.
        images: training images ``[V, H, W, 3]`` float32 in [0, 1], or a list of ``[H, W, 3]``.
        center: [3] the region of interest's centre (internal frame), for neighbour selection.
        pixels: reference pixels drawn per call (with ``fraction``: at most).
        fraction: when given, a call on an ``H x W`` view draws ``min(pixels, ceil(fraction * H * W))``
            reference pixels; ``None`` draws ``pixels``.
        patch: window side in pixels (odd).
        seed: pixel and neighbour draws (deterministic given it and the iteration).

    Raises:
        ValueError: ``patch`` not odd and >= 3, ``pixels`` < 1, ``fraction`` not in (0, 1].
    """

    def __init__(self, cameras: list[Camera], images, center: np.ndarray, *, pixels: int = 4096,
                 fraction: float | None = None, patch: int = 7, seed: int = 0):
        if patch < 3 or patch % 2 == 0:
            raise ValueError(f"patch must be odd and >= 3, got {patch!r}")
        if pixels < 1:
            raise ValueError(f"pixels must be >= 1, got {pixels!r}")
        if fraction is not None and not 0.0 < fraction <= 1.0:
            raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
        self.cameras = cameras
        self.images = images
        self.neighbours = select_neighbours(cameras, np.asarray(center, np.float64))
        self.pixels = int(pixels)
        self.fraction = None if fraction is None else float(fraction)
        self.half = patch // 2
        self.seed = int(seed)
        self._cam = TorchCams(cameras)
        self._grays: dict[int, torch.Tensor] = {}
        self._stats: dict[tuple[int, torch.device], ReferenceWindows] = {}
        self._rows: dict[tuple, torch.Tensor] = {}  # (reference, source, device) -> source row
        self._grays_on: dict[tuple, torch.Tensor] = {}  # (view, device) -> grey image there
        self._generators: dict[torch.device, torch.Generator] = {}

    def has_neighbours(self, vi: int) -> bool:
        """View ``vi`` has a neighbour to compare with."""
        return len(self.neighbours[vi]) > 0

    def count(self, height: int, width: int) -> int:
        """Reference pixels a call draws on a ``height x width`` view."""
        if self.fraction is None:
            return self.pixels
        return max(1, min(self.pixels, math.ceil(self.fraction * height * width)))

    def _gray_of(self, i: int) -> torch.Tensor:
        g = self._grays.get(i)
        if g is None:
            g = self._grays[i] = gray(self.images[i].float())
        return g

    def _gray_on(self, i: int, device: torch.device) -> torch.Tensor:
        g = self._grays_on.get((i, device))
        if g is None:
            g = self._grays_on[(i, device)] = self._gray_of(i).to(device)
        return g

    def _view_stats(self, vi: int, device: torch.device) -> ReferenceWindows:
        """What every window of view ``vi`` reads whatever its plane (made once per view and device): the grey
        image, per pixel the mean and variance [H, W] of the grey levels of the window centred there (zero
        within ``half`` of the border, where no window is drawn), the ray directions and their lengths."""
        key = (vi, device)
        st = self._stats.get(key)
        if st is None:
            g = self._gray_of(vi).to(device, torch.float64)[None, None]
            k, h = 2 * self.half + 1, self.half
            # float64 moments: E[x^2] - E[x]^2 of a flat window cancels to ~1e-8 in float32, near _MIN_STD^2
            mean = F.avg_pool2d(g, k, stride=1)
            var = (F.avg_pool2d(g * g, k, stride=1) - mean * mean).clamp_min(0.0)
            pad = (h, h, h, h)
            dirs = self._cam(vi, device).dirs
            st = self._stats[key] = ReferenceWindows(self._gray_on(vi, device), F.pad(mean, pad)[0, 0].float(),
                                                     F.pad(var, pad)[0, 0].float(), dirs, dirs.norm(dim=-1))
        return st

    def _pick(self, vi: int, seed: int) -> list[int]:
        """The neighbours of ``vi`` scored at this draw (indices into the training views)."""
        nb = self.neighbours[vi]
        pick = torch.randperm(len(nb), generator=torch.Generator().manual_seed(seed))[:_DRAWN_NEIGHBOURS].tolist()
        return [nb[j] for j in pick]

    def _sources(self, vi: int, pick: list[int], device: torch.device) -> tuple[list[torch.Tensor], torch.Tensor]:
        """The grey images of the views ``pick`` on ``device`` and their rows for :func:`window_ncc_costs` seen
        from view ``vi``. Each grey image is copied to the device once and every (reference, source) row at the
        first call: the draws that follow only gather device tensors (no host transfer in the loop)."""
        if (vi, pick[0], device) not in self._rows:
            self._all_rows(device)
        rows = [self._rows[(vi, j, device)] for j in pick]
        return [self._gray_on(j, device) for j in pick], torch.stack(rows)

    def _all_rows(self, device: torch.device) -> None:
        """Every (reference, neighbour) row, made on the CPU and copied to ``device`` in one transfer (one
        copy per pair cost three host synchronisations each, spread over the fit's first thousand iterations)."""
        pairs = [(vi, j) for vi, nb in enumerate(self.neighbours) for j in nb]
        if not pairs:
            return
        table = torch.stack([source_params(self.cameras[vi], self.cameras[j]) for vi, j in pairs]).to(device)
        for k, pair in enumerate(pairs):
            self._rows[(*pair, device)] = table[k]

    def _plane_costs(self, vi: int, py: torch.Tensor, px: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor,
                     alpha: torch.Tensor, pick: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Best ``1 - NCC`` over the neighbours ``pick`` of the windows centred on pixels ``(py, px)`` of view
        ``vi`` mapped through the planes of the rendered z-depth ``depth`` [H, W] and normal ``normal``
        [H, W, 3] at their centres (differentiable in both), and which windows count (positive depth, not
        grazing, textured, ``alpha`` [H, W] at least one half): ``(cost [P], ok [P] 0/1)``. A neighbour that
        does not see a window scores 2; a window that does not count is not scored (2, no gradient)."""
        images, params = self._sources(vi, pick, depth.device)
        return _window_costs(depth, normal, alpha,
                             Windows(py, px, self._view_stats(vi, depth.device), tuple(images), params, self.half))

    @torch.no_grad()
    def prefers(self, it: int, vi: int, depth_a: torch.Tensor, normal_a: torch.Tensor, depth_b: torch.Tensor,
                normal_b: torch.Tensor, mask: torch.Tensor, margin: float) -> torch.Tensor:
        """Pixels of ``mask`` where the photographs prefer plane ``a`` to plane ``b`` by more than ``margin``.

        For every pixel of ``mask`` at least ``half`` pixels inside view ``vi``, the window through each
        per-pixel plane (depth ``[H, W]`` z-depth and normal ``[H, W, 3]``, internal frame) is scored against
        the same drawn neighbours (:meth:`_plane_costs`); a pixel is returned where ``a``'s window counts and
        correlates (best cost under ``_MAX_COST``), ``b``'s window counts, and ``b``'s best cost exceeds
        ``a``'s by more than ``margin`` (in ``1 - NCC``). Everywhere else (no texture, no neighbour, the
        border, a plane behind the camera) nothing is said: ``False``. Not differentiable (a gate).

        Returns:
            bool ``[H, W]`` on ``mask``'s device. One host read (the pixels of ``mask``).
        """
        out = torch.zeros_like(mask)
        ref = self._cam(vi, mask.device)
        h = self.half
        if 2 * h >= ref.H or 2 * h >= ref.W or not self.neighbours[vi]:
            return out
        inner = torch.zeros_like(mask)
        inner[h:ref.H - h, h:ref.W - h] = True
        py, px = (mask & inner).nonzero(as_tuple=True)
        if py.numel() == 0:
            return out
        pick = self._pick(vi, self.seed * 1_000_003 + it)
        covered = torch.ones_like(depth_a)  # the caller's mask says which pixels count
        ca, oka = self._plane_costs(vi, py, px, depth_a, normal_a, covered, pick)
        cb, okb = self._plane_costs(vi, py, px, depth_b, normal_b, covered, pick)
        out[py, px] = (oka > 0) & (okb > 0) & (ca < _MAX_COST) & (cb - ca > margin)
        return out

    def draw(self, it: int, vi: int, device: torch.device) -> Windows | None:
        """The windows of training view ``vi`` scored at iteration ``it`` (pixels drawn on ``device`` by a
        generator there seeded from ``it``, neighbours drawn likewise), or ``None`` when the view has no neighbour
        or is too small for a window. No host synchronisation."""
        ref = self._cam(vi, device)
        H, W, h = ref.H, ref.W, self.half
        if 2 * h >= H or 2 * h >= W or not self.neighbours[vi]:
            return None
        seed = self.seed * 1_000_003 + it
        g = self._generators.get(device)
        if g is None:
            g = self._generators[device] = torch.Generator(device)
        g.manual_seed(seed)
        count = self.count(H, W)
        py = torch.randint(h, H - h, (count,), generator=g, device=device)
        px = torch.randint(h, W - h, (count,), generator=g, device=device)
        images, params = self._sources(vi, self._pick(vi, seed), device)
        return Windows(py, px, self._view_stats(vi, device), tuple(images), params, h)

    def __call__(self, it: int, vi: int, median_depth: torch.Tensor, normal: torch.Tensor,
                 alpha: torch.Tensor) -> torch.Tensor:
        """The term for training view ``vi`` at iteration ``it`` (a scalar tensor, 0 when nothing counts):
        :func:`ncc_loss` of :meth:`draw`'s windows.

        Args:
            it: iteration (seeds the draws).
            vi: reference training view.
            median_depth: rendered z-depth ``[H, W]`` float32 (differentiable).
            normal: rendered alpha-weighted world normal ``[H, W, 3]`` (differentiable).
            alpha: rendered opacity ``[H, W]`` (only its value is used).
        """
        w = self.draw(it, vi, median_depth.device)
        if w is None:
            return median_depth.sum() * 0.0
        return ncc_loss(median_depth, normal, alpha, w)
