# SPDX-License-Identifier: Apache-2.0
"""Stage 1: the initial surfels, from the scene's points, plane-sweep stereo
(:mod:`wtopo.geometry.mvs`) or the cameras' common volume.

Without points, candidate positions fill the normalised region of interest and are kept where
the masks' visual hull (or, without masks, 90 % of the camera frusta) contains them, the test
:meth:`wtopo.Scene.normalization` uses to find the region itself.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree

from .._profile import section
from ..geometry.region import carve
from .background import BackgroundState, background_surfels, prune_near_cameras, shells_wanted, uncovered_pixels
from .config import FitConfig, InitConfig, InitSource
from .surfels import Surfels

__all__ = ["scene_surfels", "initial_surfels", "stereo_points", "common_volume_points", "projected_colors",
           "spread_subset", "revise_plan", "MIN_MVS_POINTS", "INIT_OPACITY"]

INIT_OPACITY = 0.3
"""Opacity of every initial surfel (scene points, stereo, random and background ones), in (0, 1)."""

_CPU_STEREO_VIEWS = 24  # views a CPU fit sweeps (evenly spaced): the points are thinned to num_points anyway
MIN_MVS_POINTS = 100  # fewer confirmed stereo points than this: the capture is too untextured, use CAMERAS

_SCALE_NEIGHBOURS = 3  # initial scale = mean distance to this many nearest neighbours (3DGS)
_MAX_INIT_SCALE = 0.05  # no initial surfel wider than 5 % of the unit cube (isolated points)


def _boundary(cells: np.ndarray, lo: np.ndarray, cell: np.ndarray, res: int) -> np.ndarray:
    """The cells of ``cells`` (centres [P, 3]) with a face neighbour outside the set."""
    idx = np.floor((cells - lo) / cell).astype(np.int64)
    occ = np.zeros((res + 2,) * 3, dtype=bool)
    occ[idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1] = True
    i, j, k = idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1
    inner = (occ[i - 1, j, k] & occ[i + 1, j, k] & occ[i, j - 1, k] & occ[i, j + 1, k]
             & occ[i, j, k - 1] & occ[i, j, k + 1])
    return cells[~inner]


def common_volume_points(scene, n: int, generator: torch.Generator) -> np.ndarray:
    """About ``n`` points [P, 3] in the cameras' common volume of the normalised ``scene``.

    With masks the points lie in the boundary cells of the visual hull (the surface is there or
    inside it, and a surface start converges far faster than a filled volume); without masks
    they fill the region seen by 90 % of the cameras.
    """
    masks = None if scene.masks is None else scene.masks.detach().cpu().numpy().astype(bool)
    lo, hi = np.zeros(3), np.ones(3)
    res = 16
    kept = carve(scene.cameras, masks, lo, hi, res, footprint=False)
    if masks is not None:
        kept = _boundary(kept, lo, (hi - lo) / res, res)
    # refine the grid until it holds enough cells (the hull may fill a small part of the cube)
    while len(kept) < n and res < 128:
        res *= 2
        kept = carve(scene.cameras, masks, lo, hi, res, footprint=False)
        if masks is not None:
            kept = _boundary(kept, lo, (hi - lo) / res, res)
    if len(kept) == 0:
        raise ValueError("the cameras' common volume (visual hull of the masks, or 90 % of the frusta) is empty "
                         "inside the normalised scene; give the scene init points or bounds")
    cell = (hi - lo) / res
    idx = torch.randint(0, len(kept), (n,), generator=generator).numpy()
    jitter = (torch.rand(n, 3, generator=generator).numpy() - 0.5) * cell
    return kept[idx] + jitter


def projected_colors(scene, points: np.ndarray) -> np.ndarray:
    """Mean image colour [P, 3] of each point over the views it projects into (inside the mask
    when masks exist); mid grey where no view sees it. Occlusion is ignored: a start, not a fit."""
    acc = np.zeros_like(points)
    cnt = np.zeros(len(points))
    images = scene.images.detach().cpu().numpy()
    masks = None if scene.masks is None else scene.masks.detach().cpu().numpy()
    for i, cam in enumerate(scene.cameras):
        uv, z = cam.project(points)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        if masks is not None:
            ok[ok] &= masks[i][v[ok], u[ok]]
        acc[ok] += images[i][v[ok], u[ok]]
        cnt[ok] += 1
    out = np.full_like(points, 0.5)
    seen = cnt > 0
    out[seen] = acc[seen] / cnt[seen, None]
    return out


_SPREAD_BITS = 12  # the finest grid of spread_subset: 2**12 cells per side


_MORTON_STEPS = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F), (4, 0x10C30C30C30C30C3),
                 (2, 0x1249249249249249))  # spreading 21 bits to every third bit: shift, then mask


def _morton(q: torch.Tensor) -> torch.Tensor:
    """Interleaved bits of non-negative integer coordinates ``q`` [P, 3] int64 of at most 21 bits each, int64 [P]
    (bit ``b`` of axis ``a`` at bit ``3 b + a``): the points of one cell of side ``2**s`` finest cells share the
    code's bits above ``3 * s``."""
    code = torch.zeros(len(q), dtype=torch.int64, device=q.device)
    for a in range(3):
        x = q[:, a] & 0x1FFFFF
        for shift, mask in _MORTON_STEPS:
            x = (x | (x << shift)) & mask
        code |= x << a
    return code


def spread_subset(points: np.ndarray, n: int, generator: torch.Generator,
                  device: torch.device | str = "cpu") -> np.ndarray:
    """Indices of at most ``n`` of ``points`` [P, 3] spread evenly in space: one random point per
    cell of the coarsest grid that has at least ``n`` occupied cells (dense image regions would
    otherwise take the whole budget).

    The grids are the powers of two up to ``2**12`` cells per side over the points' bounding cube. One
    sort by Morton code serves every grid (a cell's points are contiguous in that order at every level),
    on ``device`` (the fit's: the millions of points of a GPU's stereo take milliseconds there, a second on
    the host), with one host read for every level's cell count. ``generator`` (CPU) draws the same points on
    any device."""
    if len(points) <= n:
        return np.arange(len(points))
    dev = torch.device(device)
    p = torch.as_tensor(np.asarray(points, np.float64)).to(dev)
    lo = p.min(0).values
    span = (p.max(0).values - lo).max()
    span = torch.where(span > 0, span, torch.ones_like(span))
    order = torch.randperm(len(p), generator=generator).to(dev)
    # finest-grid coordinates in [0, 2**12]: a coarser grid's are these shifted right, exactly, since
    # scaling by a power of two is exact in floating point (the top face's points sit in an extra cell). The span
    # is a tensor: CUDA divides by a host scalar as a product with its reciprocal, which can move a point a cell
    q = torch.floor((p[order] - lo) / span * (1 << _SPREAD_BITS)).long()
    code, by_code = torch.sort(_morton(q), stable=True)
    new_cell = [code[1:] >> (3 * (_SPREAD_BITS - level)) != code[:-1] >> (3 * (_SPREAD_BITS - level))
                for level in range(1, _SPREAD_BITS + 1)]  # cells per side 2, 4, ..., 4096
    cells = (torch.stack([c.sum() for c in new_cell]) + 1).tolist()
    level = next((i for i, c in enumerate(cells) if c >= n), len(cells) - 1)
    cell = torch.cumsum(torch.cat([new_cell[level].new_zeros(1), new_cell[level]]).long(), 0)
    first = torch.full((cells[level],), len(p), dtype=torch.int64, device=dev).scatter_reduce_(
        0, cell, by_code, "amin")  # each cell's first point in the random order
    pick = order[torch.sort(first).values]
    if len(pick) > n:
        pick = pick[torch.randperm(len(pick), generator=generator)[:n].to(dev)]
    return np.sort(pick.cpu().numpy())


def stereo_points(scene, layout, device):
    """Plane-sweep stereo's confirmed points of ``scene`` (:class:`~wtopo.geometry.mvs.MVSPoints`, internal
    frame, not thinned), swept over ``layout``'s region of interest (the unit cube without one); a CPU
    device sweeps at most ``_CPU_STEREO_VIEWS`` views. Fewer than :data:`MIN_MVS_POINTS` points: the capture
    is too untextured to start from them."""
    from ..geometry.mvs import plane_sweep_points

    lo, hi = (np.zeros(3), np.ones(3)) if layout is None else (layout.roi_lower, layout.roi_upper)
    near = 0.01 if layout is None else layout.near
    max_views = None if torch.device(device).type == "cuda" else _CPU_STEREO_VIEWS
    return plane_sweep_points(scene.cameras, scene.images, lo, hi, near=near, device=device, max_views=max_views)


def _thinned_stereo(found, cfg: InitConfig, generator, device: torch.device | str = "cpu"):
    """``(points, colours, normals)`` of ``found`` thinned to ``cfg.num_points``; ``None`` (with a warning)
    when too few depths are confirmed."""
    if len(found.points) < MIN_MVS_POINTS:
        warnings.warn(f"plane-sweep stereo confirmed {len(found.points)} points (< {MIN_MVS_POINTS}): the images are "
                      "too untextured; starting from random points in the cameras' common volume", RuntimeWarning,
                      stacklevel=3)
        return None
    keep = spread_subset(found.points, int(cfg.num_points), generator, device)
    return found.points[keep], found.colors[keep], found.normals[keep]


def initial_surfels(scene, cfg: InitConfig, source: InitSource | str, *, sh_degree: int, device: torch.device,
                    generator: torch.Generator, layout=None, stereo=None) -> Surfels:
    """Surfels for stage 1 in the internal frame of the normalised ``scene``.

    Scales are the mean distance to ``_SCALE_NEIGHBOURS`` nearest neighbours; rotations random
    (stereo points: facing their reference camera along the depth map's normal); colours the
    scene's point colours, the stereo reference pixel's, or the mean colour the points project to.
    ``layout`` (:class:`~wtopo.fitting.scene_kind.SceneLayout`) gives the stereo sweep its region of
    interest and near distance; without it, the unit cube and 1 % of it. ``stereo`` is
    :func:`stereo_points`' result when the caller has it already (source ``mvs``; computed here otherwise).
    """
    normals = None
    thinned = None
    if source == InitSource.MVS:
        thinned = _thinned_stereo(stereo_points(scene, layout, device) if stereo is None else stereo, cfg, generator,
                                  device)
    if thinned is not None:
        pts, cols, normals = thinned
    elif source in (InitSource.MVS, InitSource.CAMERAS):
        pts = common_volume_points(scene, int(cfg.num_points), generator)
        cols = projected_colors(scene, pts)
    elif source == InitSource.POINTS:
        if scene.points is None or len(scene.points) == 0:
            raise ValueError("init.source is 'points' but the scene has no points")
        pts = np.asarray(scene.points, np.float64)
        cols = (np.asarray(scene.point_colors, np.float64) if scene.point_colors is not None
                else np.full_like(pts, 0.5))
    else:
        raise ValueError(f"init source must be 'points', 'mvs' or 'cameras', got {source!r}")
    k = min(_SCALE_NEIGHBOURS + 1, len(pts))
    if k > 1:
        d, _ = cKDTree(pts).query(pts, k=k, workers=-1)
        scale = np.clip(d[:, 1:].mean(axis=1), 1e-6, _MAX_INIT_SCALE)
    else:
        scale = np.full(len(pts), 0.01)
    return Surfels.from_points(torch.as_tensor(pts, dtype=torch.float32, device=device),
                               torch.as_tensor(cols, dtype=torch.float32, device=device),
                               scales=torch.as_tensor(scale, dtype=torch.float32, device=device),
                               normals=None if normals is None else torch.as_tensor(normals, dtype=torch.float32,
                                                                                     device=device),
                               opacity=INIT_OPACITY, sh_degree=sh_degree, generator=generator)


def scene_surfels(scene, cfg: FitConfig, layout, device: torch.device, generator: torch.Generator,
                  background: BackgroundState | None, record=None, forced: bool = False) -> Surfels:
    """The fit's initial surfels of ``scene`` (its training views): from ``cfg.init.source`` (plane-sweep stereo's
    confirmed points for ``mvs``), plus ``cfg.init.background_points`` background shells seeded where the stereo
    explained nothing, unless most of those pixels are untextured (:func:`~.background.shells_wanted`; ``forced``:
    the configuration set their number, which stands), none of them within ``background``'s near distance of a
    camera. ``record(event, **fields)`` (optional) receives a
    "background_shells" event: the shells seeded, the untextured share of the unexplained pixels (``None`` without
    any, or without stereo points) and the surfels the lens prune then removed. Profiled as "init_seed" and
    "init_shells" (the stereo's own sections inside the first)."""
    with section("init_seed"):
        stereo = stereo_points(scene, layout, device) if cfg.init.source == InitSource.MVS else None
        s = initial_surfels(scene, cfg.init, cfg.init.source, sh_degree=int(cfg.sh_degree), device=device,
                            generator=generator, layout=layout, stereo=stereo)
    n_bg = int(cfg.init.background_points)
    if n_bg > 0:  # the shells seed only where the stereo explained nothing
        with section("init_shells"):
            seen = None if stereo is None or len(stereo.points) < MIN_MVS_POINTS else stereo.points
            free = None if seen is None else uncovered_pixels(scene.cameras, seen, device, generator)
            wanted, share = (True, None) if free is None else shells_wanted(scene.images, free)
            wanted = wanted or forced
            seeded = lens = 0
            if wanted:
                bg = background_surfels(scene, layout, n_bg, sh_degree=s.sh_degree, opacity=INIT_OPACITY,
                                        device=device, generator=generator, free=free)
                s.append(*bg.take(slice(None)))
                seeded = len(bg)
                if background is not None:  # nothing starts on a lens
                    lens = prune_near_cameras(s, background)
            if record is not None:
                record("background_shells", seeded=seeded,
                       untextured_share=None if share is None else round(share, 4), lens_pruned=lens)
    return s


def revise_plan(plan, events: list[dict]):
    """``plan`` with the background shells as the initial surfels' ``background_shells`` event in ``events`` found
    them: none seeded where the plan had some, for the untextured share (``plan`` itself otherwise)."""
    ev = next((e for e in events if e.get("event") == "background_shells"), None)
    if ev is None or ev["seeded"] or not plan.background_points:
        return plan
    share = ev.get("untextured_share")
    why = ("scene, but the stereo left no pixel unexplained" if share is None else
           f"scene, but {share:.0%} of the pixels the stereo left unexplained are untextured: near surfaces and a "
           "backdrop, not a far scene")
    return plan.revised("background_points", 0, why + " (no shells)")

