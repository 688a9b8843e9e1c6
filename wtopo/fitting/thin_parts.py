# SPDX-License-Identifier: Apache-2.0
"""The co-evolution's thin-part rule: how much of the proxy the training views see through parts a few
Poisson cells thick, and what the co-evolution does about it.

The proxy is the Poisson surface of the surfels splatted with a Gaussian of ``mesh.sigma`` cells: a
part about ``2 sigma + 1`` cells thick or less lies within the splat's reach from both of its sides, so
its surface is the smoothed blend of two opposite sheets, not theirs (:func:`thin_cells`). Where much
of what the views see is such parts (a chair's legs, seat and back-rest at the CPU default's 64^3
proxy), the mesh terms pull the surfels to that blend. The rule first gives the proxy a grid twice as
fine, which resolves such parts at twice the cells; where even that grid leaves too much thin, the mesh
terms stay off.
"""

from __future__ import annotations

import numpy as np
import torch

from .config import FitConfig
from .proxy import ProxyMesh
from .surfels import Surfels

__all__ = ["MAX_RESOLUTION", "thin_cells", "thin_parts", "thin_share"]

MAX_RESOLUTION = 256  # the finest proxy grid the rule gives (the plan's finest: CUDA at 512 px)
_VIEWS = 8  # training views (evenly spaced) the share is measured from


def thin_cells(cfg: FitConfig) -> float:
    """Below how many Poisson cells along a ray a part is thin: the splat's reach of ``mesh.sigma`` cells
    from each of its two sides plus the cell the surface lies in (3 at the default sigma of 1)."""
    return 2.0 * float(cfg.mesh.sigma) + 1.0


def thin_share(proxy: ProxyMesh, surfels: Surfels, cameras, cfg: FitConfig) -> float | None:
    """The fraction of ``proxy``'s pixels, seen from up to 8 evenly spaced ``cameras``, whose ray crosses
    fewer than :func:`thin_cells` cells of the proxy of ``surfels`` (:meth:`ProxyMesh.thickness`);
    ``None`` when no proxy can be built. Discrete; a few host reads."""
    with torch.no_grad():
        pm = proxy.build(surfels)
    if pm is None:
        return None
    picks = np.unique(np.linspace(0, len(cameras) - 1, min(_VIEWS, len(cameras))).round().astype(int))
    hit = thin = 0
    limit = thin_cells(cfg)
    for i in picks:
        render, cells = proxy.thickness(pm, cameras[int(i)])
        hit += int(render.mask.sum())
        thin += int((cells < limit).sum())
    return round(thin / hit, 4) if hit else 0.0


def thin_parts(proxy: ProxyMesh, surfels: Surfels, cameras, cfg: FitConfig) -> dict:
    """Measure the proxy of ``surfels`` at the co-evolution's start and decide its grid and the mesh terms.

    Over ``losses.mesh_thin_limit`` the grid doubles (up to :data:`MAX_RESOLUTION` nodes per side) and the
    share is measured again on it; still over the limit (or no finer grid allowed), the mesh terms stay
    off for the fit.

    Args:
        proxy: the fit's proxy builder (its grid sets the cell).
        surfels: the surfels the co-evolution starts from.
        cameras: the training cameras; up to 8 evenly spaced ones are ray cast (twice each, per grid).
        cfg: the resolved configuration (``losses.mesh_thin_limit``, the mesh terms' weights).

    Returns:
        ``{}`` when the co-evolution runs no mesh terms anyway. Otherwise ``thin_share`` (:func:`thin_share`
        on the grid kept), ``resolution`` (that grid's nodes per side), ``limit``, ``mesh_terms`` (whether
        they run) and, when the rule fired, ``coarse``: the first measure's grid and its share.
    """
    lc = cfg.losses
    if not cfg.coevolution.enabled or (lc.mesh_depth <= 0 and lc.mesh_normal <= 0):
        return {}
    limit = float(lc.mesh_thin_limit)
    res = int(proxy.cfg.resolution)
    share = thin_share(proxy, surfels, cameras, cfg)
    info: dict = {"thin_share": share, "resolution": res, "limit": limit}
    if share is not None and share > limit and 2 * res <= MAX_RESOLUTION:
        fine = thin_share(proxy.with_resolution(2 * res), surfels, cameras, cfg)
        info.update(thin_share=fine, resolution=2 * res, coarse={"resolution": res, "thin_share": share})
        share = fine
    info["mesh_terms"] = share is None or share <= limit
    return info
