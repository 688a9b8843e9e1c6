# SPDX-License-Identifier: Apache-2.0
"""Which pixels of a training view show surface that other training views see too.

A photograph fixes the depth of a surface point only where a second photograph sees the same
point; where one view alone sees it (the inside of a cup from ten views), the fit's depth there is
whatever the rendering of that one photograph allows, and the proxy mesh's guess (the Poisson
surface's smooth closing of what it was given, often a lid) is no better. The co-evolution's mesh
terms pull the surfels towards that guess. This module lets them leave such pixels alone
(``losses.mesh_view_support``).

For a pixel ``p`` of view ``v`` the surfels' point ``X`` lies at the rendered (median) z-depth along
``p``'s ray. Another training view ``u`` *sees* ``X`` when ``X`` projects inside ``u``'s image, in front
of its camera, onto a pixel ``q`` rendered opaque (opacity >= 0.5) whose own rendered z-depth agrees
with ``X``'s depth in ``u`` within a tolerance (``X`` is neither hidden behind ``u``'s surface nor
floating in front of it). The pixel's support is ``1 +`` the number of other views that see ``X``.

The other views' depth maps are the last ones the fit rendered of them (the views come in a new order
every pass, so a map is up to two passes old); a view not rendered yet is rendered once, without
gradient, when first needed (the co-evolution's start, or after a resume). A map with non-finite
depths (a step the fit rolled back) sees nothing until its view is rendered again. Nothing here is
differentiable: the result is a mask.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..camera import Camera
from .mvs import _TorchCams

__all__ = ["ViewSupport"]

_ALPHA = 0.5  # a pixel of another view counts only when rendered at least this opaque


class ViewSupport:
    """Counts, per pixel of a training view, the training views that see the surfels' point there.

    Args:
        cameras: training cameras (internal frame), at the rendered resolution.
        min_views: views (the pixel's own included) that must see a point for it to count as supported;
            >= 2.
        center: [3] a point the views look at (the region of interest's centre), used only to order the
            other views by angle (the nearest first, so a densely seen pixel is settled after few views).

    Raises:
        ValueError: ``min_views`` < 2, fewer than two cameras.
    """

    def __init__(self, cameras: Sequence[Camera], *, min_views: int, center: np.ndarray):
        if int(min_views) < 2:
            raise ValueError(f"min_views must be >= 2, got {min_views!r}")
        if len(cameras) < 2:
            raise ValueError(f"cameras must hold at least 2 views, got {len(cameras)}")
        self.cameras = list(cameras)
        self.min_views = int(min_views)
        c = np.asarray(center, np.float64).reshape(3)
        dirs = np.stack([cam.center - c for cam in self.cameras])
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
        cos = dirs @ dirs.T
        # other views, the most similar viewing direction first
        self.order = [[int(j) for j in np.argsort(-cos[i], kind="stable") if j != i] for i in range(len(cameras))]
        self._maps: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._cam = _TorchCams(self.cameras)
        self.compared = 0  # pixels asked about since the last :meth:`take_counts`
        self._unsupported: torch.Tensor | None = None  # of them, those fewer than min_views views see (on the device)

    def remember(self, vi: int, depth: torch.Tensor, alpha: torch.Tensor) -> None:
        """Keep view ``vi``'s rendered z-depth and opacity [H, W] (detached) as its current maps."""
        self._maps[int(vi)] = (depth.detach(), alpha.detach())

    def supported(self, vi: int, depth: torch.Tensor, mask: torch.Tensor,
                  tolerance: float | torch.Tensor, render: Callable[[int], tuple[torch.Tensor, torch.Tensor]]
                  | None = None) -> torch.Tensor:
        """Pixels [H, W] bool of ``mask`` whose surfel point at least ``min_views`` training views see.

        Args:
            vi: the view the pixels belong to.
            depth: its rendered z-depth [H, W] (scene units; only the value is used).
            mask: pixels [H, W] bool to decide; the others come back ``False``.
            tolerance: largest disagreement, in scene units of z-depth in the other view, at which that
                view still sees the point (a scalar, or [H, W] per pixel of ``vi``).
            render: ``u -> (z-depth [H, W], opacity [H, W])`` of another view, called (once) for a view
                with no kept maps; ``None`` leaves such views out of the count.
        """
        out = torch.zeros_like(mask, dtype=torch.bool)
        py, px = torch.nonzero(mask, as_tuple=True)
        n = int(py.numel())
        self.compared += n
        if n == 0:
            return out
        dev, dt = depth.device, depth.dtype
        ref = self._cam(vi, dev, dt)
        d = depth.detach()[py, px]
        x = ref.origin[py, px] + ref.dirs[py, px] * d[:, None]  # [P, 3] the surfels' points
        tol = torch.as_tensor(tolerance, dtype=dt, device=dev)
        tol = tol[py, px] if tol.ndim == 2 else tol.expand(n)
        need = self.min_views - 1
        count = torch.zeros(n, dtype=torch.int32, device=dev)
        pending = torch.arange(n, device=dev)  # points still short of the views they need
        for u in self.order[vi]:
            maps = self._maps.get(u)
            if maps is None:
                if render is None:
                    continue
                du, au = render(u)
                self.remember(u, du, au)
                maps = self._maps[u]
            du, au = maps
            cu = self._cam(u, dev, dt)
            pu, pv, z = cu.project(x[pending])
            ix, iy = torch.floor(pu).long(), torch.floor(pv).long()
            inside = (z > 0) & (ix >= 0) & (ix < cu.W) & (iy >= 0) & (iy < cu.H)
            ix, iy = ix.clamp(0, cu.W - 1), iy.clamp(0, cu.H - 1)
            dq = du[iy, ix].to(dt)
            sees = inside & (au[iy, ix] >= _ALPHA) & (dq > 0) & ((z - dq).abs() <= tol[pending])
            count[pending] += sees.to(torch.int32)
            pending = pending[count[pending] < need]
            if pending.numel() == 0:
                break
        ok = count >= need
        short = (~ok).sum()  # kept on the device: read by take_counts only
        self._unsupported = short if self._unsupported is None else self._unsupported + short
        out[py, px] = ok
        return out

    def counts_state(self) -> tuple:
        """The counts as they stand, for :meth:`restore_counts` (a step computed again counts once)."""
        return self.compared, self._unsupported

    def restore_counts(self, state: tuple) -> None:
        """Put back the counts :meth:`counts_state` returned."""
        self.compared, self._unsupported = state

    def take_counts(self) -> dict:
        """``{"compared": pixels, "unsupported": pixels, "share": unsupported / compared}`` since the last
        call; clears them."""
        c, u = self.compared, 0 if self._unsupported is None else int(self._unsupported)
        self.compared, self._unsupported = 0, None
        return {"compared": c, "unsupported": u, "share": round(u / c, 4) if c else 0.0}
