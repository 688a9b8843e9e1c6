# SPDX-License-Identifier: Apache-2.0
"""Multi-view geometric consistency of the rendered depth (PGSR's forward-backward reprojection).

Each training view is fitted against its own photograph, so two views may render the same
surface at different depths and both reproduce their pictures. This term ties the views' depth
maps together. For sampled pixels ``p`` of the reference view it takes the rendered point ``X``
(median depth along ``p``'s ray), projects it into a neighbouring view at ``q``, lifts ``q`` back
to 3-D with the neighbour's rendered depth there (``Y``), and projects ``Y`` into the reference
view at ``p'``. Where the two depth maps describe one surface the round trip closes: ``p' = p``.
The loss is the pixel distance ``|p' - p|``.

* As in PGSR, pixels whose round trip misses by ``max_error`` pixels or more (occlusion, a view that
  does not see the point) carry no loss, and each pixel's error is weighted by ``exp(-error)``
  (detached), so the term trusts near-consistent pixels most.
* The neighbour (one per call, drawn among :func:`wtopo.fitting.mvs.select_neighbours`, seeded by the
  iteration) is rendered by the caller without gradient: it is the target, and only the reference
  view's depth moves. PGSR back-propagates into both views; one render without a backward pass
  costs less on the CPU, and every view is the reference in its turn.
* Rays and projection are the cameras' own (:class:`wtopo.fitting.mvs._TorchCam`), so distortion
  and skew need no undistortion; the neighbour's depth, opacity and rays at the continuous ``q`` are
  bilinear samples (the rays are exact there for a pinhole camera, whose rays are linear in the
  pixel).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..camera import Camera
from .mvs import _TorchCam, _TorchCams, select_neighbours

__all__ = ["ForwardBackwardDepth"]

_ALPHA = 0.5  # pixels (reference and neighbour) rendered less opaque than this carry no loss


class ForwardBackwardDepth:
    """The forward-backward depth reprojection term for training views.

    Args:
        cameras: training cameras (internal frame), at the rendered resolution.
        center: [3] the region of interest's centre (internal frame), for neighbour selection.
        pixels: reference pixels drawn per call.
        max_error: round-trip error in pixels at or beyond which a pixel carries no loss (PGSR: 1).
        seed: pixel and neighbour draws (deterministic given it and the iteration).

    Raises:
        ValueError: ``pixels`` < 1, ``max_error`` not positive.
    """

    def __init__(self, cameras: list[Camera], center: np.ndarray, *, pixels: int = 4096, max_error: float = 1.0,
                 seed: int = 0):
        if pixels < 1:
            raise ValueError(f"pixels must be >= 1, got {pixels!r}")
        if not max_error > 0:
            raise ValueError(f"max_error must be > 0 pixels, got {max_error!r}")
        self.cameras = cameras
        self.neighbours = select_neighbours(cameras, np.asarray(center, np.float64))
        self.pixels = int(pixels)
        self.max_error = float(max_error)
        self.seed = int(seed)
        self._tcams = _TorchCams(cameras)
        self._generators: dict[torch.device, torch.Generator] = {}

    def has_neighbours(self, vi: int) -> bool:
        """View ``vi`` has a neighbour to compare with."""
        return len(self.neighbours[vi]) > 0

    def neighbour(self, it: int, vi: int) -> int:
        """The neighbour of view ``vi`` used at iteration ``it`` (the caller renders it)."""
        nb = self.neighbours[vi]
        g = torch.Generator().manual_seed(self._seed(it) + 1)
        return nb[int(torch.randint(len(nb), (1,), generator=g))]

    def _seed(self, it: int) -> int:
        return self.seed * 1_000_003 + 7_919 * int(it)

    def _cam(self, i: int, device: torch.device, dtype: torch.dtype) -> _TorchCam:
        """Camera ``i`` on ``device`` in ``dtype`` (the depth's: float64 for gradient checks)."""
        c = self._tcams(i, device, dtype)
        if not hasattr(c, "rays"):
            c.rays = torch.cat([c.origin, c.dirs], -1).permute(2, 0, 1)[None]  # [1, 6, H, W] to sample at q
        return c

    def errors(self, it: int, vi: int, depth: torch.Tensor, alpha: torch.Tensor, nj: int, nb_depth: torch.Tensor,
               nb_alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(error [P], valid [P] bool)``: the round-trip error in reference pixels at the drawn pixels and
        which of them could be measured (both views opaque there, the point in front of the neighbour and
        inside its image). Arguments as :meth:`__call__`."""
        dev = depth.device
        ref, src = self._cam(vi, dev, depth.dtype), self._cam(nj, dev, depth.dtype)
        g = self._generators.get(dev)
        if g is None:
            g = self._generators[dev] = torch.Generator(dev)
        g.manual_seed(self._seed(it))
        py = torch.randint(0, ref.H, (self.pixels,), generator=g, device=dev)
        px = torch.randint(0, ref.W, (self.pixels,), generator=g, device=dev)
        d = depth[py, px]
        x = ref.origin[py, px] + ref.dirs[py, px] * d[:, None]  # forward: the reference's point [P, 3]
        u, v, z = src.project(x)
        inside = (z > 0) & (u >= 0) & (u <= src.W) & (v >= 0) & (v <= src.H)
        grid = src.grid(u, v)[None, None]  # [1, 1, P, 2]

        def at_q(maps):  # [1, C, H', W'] -> [C, P], bilinear at the neighbour's pixels q
            return F.grid_sample(maps, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]

        dn, an = at_q(torch.stack([nb_depth, nb_alpha])[None])
        r = at_q(src.rays)
        on, rn = r[:3].T, r[3:].T
        y = on + rn * dn[:, None]  # backward: the neighbour's point along its ray through q
        pu, pv, pz = ref.project(y)
        err = torch.stack([pu - (px.to(pu.dtype) + 0.5), pv - (py.to(pv.dtype) + 0.5)], -1).norm(dim=-1)
        valid = ((alpha.detach()[py, px] >= _ALPHA) & (d.detach() > 0) & inside & (an.detach() >= _ALPHA)
                 & (dn.detach() > 0) & (pz.detach() > 0))
        return err, valid

    def __call__(self, it: int, vi: int, depth: torch.Tensor, alpha: torch.Tensor, nj: int, nb_depth: torch.Tensor,
                 nb_alpha: torch.Tensor) -> torch.Tensor:
        """The term for reference view ``vi`` at iteration ``it`` (a scalar tensor in pixels, 0 when no
        pixel counts): the mean of ``exp(-e) e`` over drawn pixels whose round-trip error ``e`` is below
        ``max_error``.

        Args:
            it: iteration (seeds the draws).
            vi: reference training view.
            depth: its rendered z-depth ``[H, W]`` float32 (differentiable; float64 runs the whole round
                trip in float64).
            alpha: its rendered opacity ``[H, W]`` (only the value is used).
            nj: the neighbour view (:meth:`neighbour`).
            nb_depth: the neighbour's rendered z-depth ``[H', W']`` (a target: treated as constant in
                value, though the sampling position carries the reference depth's gradient).
            nb_alpha: the neighbour's rendered opacity ``[H', W']``.
        """
        err, valid = self.errors(it, vi, depth, alpha, nj, nb_depth.detach(), nb_alpha.detach())
        use = valid & (err.detach() < self.max_error)
        w = torch.exp(-err.detach()) * use.to(err.dtype)
        e = torch.where(use, err, torch.zeros_like(err))  # no 0 * inf from a point projected at infinity
        return (w * e).sum() / use.sum().clamp_min(1).to(err.dtype)
