# SPDX-License-Identifier: Apache-2.0
"""The co-evolution's thin-part rule: how much of the proxy the training views see through parts a few
Poisson cells thick, and whether the mesh terms run.

The proxy is the Poisson surface of the surfels splatted with a Gaussian of ``mesh.sigma`` cells: a
part about ``2 sigma + 1`` cells thick or less lies within the splat's reach from both of its sides, so
its surface is the smoothed blend of two opposite sheets, not theirs (:func:`thin_cells`). Where most
of what the views see is such parts (a chair's legs, seat and back-rest at the CPU default's 64^3 proxy), the mesh terms
pull the surfels to that blend.
"""

from __future__ import annotations

import numpy as np
import torch

from .config import FitConfig
from .proxy import ProxyMesh
from .surfels import Surfels

__all__ = ["thin_cells", "thin_parts"]

_VIEWS = 8  # training views (evenly spaced) the share is measured from


def thin_cells(cfg: FitConfig) -> float:
    """Below how many Poisson cells along a ray a part is thin: the splat's reach of ``mesh.sigma`` cells
    from each of its two sides plus the cell the surface lies in (3 at the default sigma of 1)."""
    return 2.0 * float(cfg.mesh.sigma) + 1.0


def thin_parts(proxy: ProxyMesh, surfels: Surfels, cameras, cfg: FitConfig) -> dict:
    """Measure the proxy of ``surfels`` at the co-evolution's start and decide the mesh terms.

    Args:
        proxy: the fit's proxy builder (its grid sets the cell).
        surfels: the surfels the co-evolution starts from.
        cameras: the training cameras; up to 8 evenly spaced ones are ray cast (twice each).
        cfg: the resolved configuration (``losses.mesh_thin_limit``, the mesh terms' weights).

    Returns:
        ``{}`` when the co-evolution runs no mesh terms anyway. Otherwise ``thin_share`` (the fraction of
        the proxy's pixels whose ray crosses fewer than :func:`thin_cells` cells of it, or ``None`` when
        no proxy could be built), ``limit`` (``losses.mesh_thin_limit``) and ``mesh_terms``: whether the
        mesh terms run (``False`` when the share exceeds the limit). Discrete; a few host reads.
    """
    lc = cfg.losses
    if not cfg.coevolution.enabled or (lc.mesh_depth <= 0 and lc.mesh_normal <= 0):
        return {}
    limit = float(lc.mesh_thin_limit)
    with torch.no_grad():
        pm = proxy.build(surfels)
    if pm is None:
        return {"thin_share": None, "limit": limit, "mesh_terms": True}
    picks = np.unique(np.linspace(0, len(cameras) - 1, min(_VIEWS, len(cameras))).round().astype(int))
    hit = thin = 0
    cells_limit = thin_cells(cfg)
    for i in picks:
        render, cells = proxy.thickness(pm, cameras[int(i)])
        hit += int(render.mask.sum())
        thin += int((cells < cells_limit).sum())
    share = thin / hit if hit else 0.0
    return {"thin_share": round(share, 4), "limit": limit, "mesh_terms": share <= limit}
