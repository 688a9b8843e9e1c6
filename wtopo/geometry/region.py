# SPDX-License-Identifier: Apache-2.0
"""Region-of-interest estimation for :meth:`wtopo.Scene.region_of_interest` (host, float64): the
visual hull of the masks, the common volume of the camera frusta, or the box of the points most
cameras see.

The hull is carved on a grid: a cell is removed when a view sees it and its projected footprint
misses that view's mask. The footprint test (not a test of the cell's centre) keeps every cell that
holds a piece of the object, however thin: an object a few pixels thick survives a coarse grid.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt

from ..camera import Camera

__all__ = ["visual_hull_box", "points_box", "carve", "mask_distances"]

_HULL_GRID = (32, 48)  # visual-hull / frustum grid resolution per axis: coarse pass, refined pass
_DEGENERATE_SPREAD = 1e-9  # camera centres closer than this (relative to the scene extent) coincide
_FORWARD_OVERLAP = 2.0  # forward-facing rigs: the frusta's common width at the focus, in rig spreads
_COLINEAR_RATIO = 1e-6  # second / first singular value of the centred camera centres below this: colinear
_PIXEL_SLACK = math.sqrt(0.5)  # px: a projected point and its pixel's centre are at most half a diagonal apart
# forward-facing rigs with images: the depth the cameras look at, measured by plane-sweep stereo on
# this many views at about this many pixels along the longer image side, over depths from / to these
# multiples of the rig-geometry guess, from the points within this fraction of the half field of view
_STEREO_VIEWS = 8
_STEREO_PIXELS = 64
_STEREO_NEAR, _STEREO_FAR = 0.05, 8.0
_STEREO_CENTRAL = 0.5


# -- region-of-interest estimation (host, float64) ------------------------------------------------
def _check_camera_spread(centers: np.ndarray, ref_len: float) -> None:
    n = len(centers)
    if n < 2:
        raise ValueError(f"estimating the region of interest from cameras needs at least 2 cameras, got {n}; "
                         "give Scene(bounds=...)")
    c = centers - centers.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[0] == 0 or sv[0] <= _DEGENERATE_SPREAD * ref_len:
        raise ValueError(f"all {n} camera centres coincide (cameras[0] at {centers[0].tolist()}); "
                         "the region of interest cannot be estimated, give Scene(bounds=...)")
    if sv[1] <= _COLINEAR_RATIO * sv[0]:
        far = int(np.argmax(np.linalg.norm(centers - centers[0], axis=1)))  # never cameras[0] itself
        raise ValueError(f"all {n} camera centres lie on one line (e.g. cameras[0] at {centers[0].tolist()}, "
                         f"cameras[{far}] at {centers[far].tolist()}); the region of interest cannot be "
                         "estimated, give Scene(bounds=...)")


def _pixel_ray_world(cam: Camera, u: float, v: float) -> np.ndarray:
    """World direction of the ray through continuous pixel coordinates (u, v)."""
    y = (v - cam.K[1, 2]) / cam.K[1, 1]
    x = (u - cam.K[0, 2] - cam.K[0, 1] * y) / cam.K[0, 0]
    xy = cam.undistort(np.array([[x, y]]))[0]
    return cam.R.T @ np.array([xy[0], xy[1], 1.0])


def _converge_point(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray | None:
    """Least-squares point closest to the lines ``origins + t dirs`` (None when near-parallel)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(axis=0)
    b = np.einsum("nij,nj->i", P, origins)
    w = np.linalg.eigvalsh(A)
    if w[0] <= 1e-6 * w[-1]:
        return None
    return np.linalg.solve(A, b)


def _project_one(cam, pts: np.ndarray):
    """Pixel (row, col) int64 indices [M], in-image flags [M] and camera-frame points [M, 3] (float64,
    world units) of ``pts`` [M, 3] in one camera."""
    pc = pts @ cam.R.T + cam.t
    if cam.distortion is None:  # pinhole fast path (same maths as Camera.project)
        z = pc[:, 2]
        zs = np.where(z > 0, z, 1.0)
        y = pc[:, 1] / zs
        u = cam.K[0, 0] * (pc[:, 0] / zs) + cam.K[0, 1] * y + cam.K[0, 2]
        v = cam.K[1, 1] * y + cam.K[1, 2]
    else:
        uv, z = cam.project(pts)
        u, v = uv[:, 0], uv[:, 1]
    ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    rows = np.clip(np.floor(v), 0, cam.height - 1).astype(np.int64)
    cols = np.clip(np.floor(u), 0, cam.width - 1).astype(np.int64)
    return rows, cols, ok, pc


def _seen_count(cameras, pts: np.ndarray) -> np.ndarray:
    """How many of ``cameras`` hold each of ``pts`` [M, 3] in their image (int [M])."""
    seen = np.zeros(len(pts), np.int64)
    for cam in cameras:
        seen += _project_one(cam, pts)[2]
    return seen


def mask_distances(masks_np: np.ndarray) -> np.ndarray:
    """Distance in pixels from every pixel centre to the nearest mask pixel's centre (0 inside).

    Args:
        masks_np: object masks, shape [N, H, W], bool; every mask non-empty.

    Returns:
        float64 [N, H, W].
    """
    return np.stack([distance_transform_edt(~m) for m in masks_np])


def carve(cameras, masks_np, lo, hi, res, *, mask_dist=None, footprint: bool = True):
    """Centres [P, 3] (float64, world units) of the cells of a ``res``^3 grid over the box ``[lo, hi]``
    that the visual hull of ``masks_np`` (bool [N, H, W]) keeps, or, for ``masks_np=None``, that 90 % of
    the camera frusta hold.

    With masks a cell is removed when some view sees its centre and the cell's projected footprint
    misses that view's mask: the footprint is the disc around the centre's pixel that holds the
    projection of the cell's bounding sphere (radius ``R``: ``R f |p| / (z (z - R))`` pixels, ``f`` the
    larger focal length, ``z`` and ``|p|`` the centre's depth and distance), plus :data:`_PIXEL_SLACK`
    twice (the centre to its pixel centre, the object to a mask pixel centre). Every cell that holds a
    piece of the object is thus kept whatever the grid size (lens distortion aside). A cell must also be
    seen by half of the views (at least 2).

    Args:
        cameras: the views, a list of N :class:`~wtopo.Camera`.
        masks_np: object masks, bool [N, H, W], or None for the frustum test.
        lo: the grid box's lower corner [3], world units.
        hi: its upper corner [3].
        res: cells per axis.
        mask_dist: :func:`mask_distances` of ``masks_np`` when already computed (float64 [N, H, W]).
        footprint: ``False`` tests the cells' centres only (a cell is removed when its centre's pixel is
            outside a mask): tighter, for sampling points near the hull's surface, but a coarse grid misses
            parts thinner than a cell.
    """
    axes = [lo[k] + (np.arange(res) + 0.5) * (hi[k] - lo[k]) / res for k in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    n = len(cameras)
    need = math.ceil(0.9 * n) if masks_np is None else max(min(2, n), math.ceil(0.5 * n))
    if masks_np is not None and footprint:
        if mask_dist is None:
            mask_dist = mask_distances(masks_np)
        radius = 0.5 * float(np.linalg.norm((np.asarray(hi) - np.asarray(lo)) / res))  # cell's bounding sphere
    # one view at a time over the cells still alive: a rejected cell, or one that can no longer reach
    # ``need`` views, is never projected again (the same cells as testing every cell in every view)
    alive = np.arange(len(g))
    seen = np.zeros(len(g), np.int64)
    for i, cam in enumerate(cameras):
        rows, cols, ok, pc = _project_one(cam, g[alive])
        seen[alive] += ok
        if masks_np is not None:
            if footprint:
                depth, dist = pc[:, 2], np.linalg.norm(pc, axis=1)
                focal = max(abs(cam.K[0, 0]), abs(cam.K[1, 1]))
                near = depth - radius
                with np.errstate(divide="ignore", invalid="ignore"):
                    reach = np.where(near > 0, radius * focal * dist / (depth * near), np.inf)
                rejected = ok & (mask_dist[i][rows, cols] > reach + 2.0 * _PIXEL_SLACK)
            else:
                rejected = ok & ~masks_np[i][rows, cols]
            alive = alive[~rejected]
        alive = alive[seen[alive] + (n - 1 - i) >= need]
    return g[alive[seen[alive] >= need]]


def _forward_focus(cameras, centers: np.ndarray, images=None) -> tuple[np.ndarray | None, float]:
    """Focus and radius for parallel optical axes (a forward-facing rig, as LLFF): along the mean
    viewing direction at depth ``d``, radius ``d / 2``.

    ``d`` is the median depth of what the middle of the pictures shows (:func:`_stereo_depth`: plane
    sweep stereo on a few downscaled views) when ``images`` are given and hold texture; otherwise a
    guess from the cameras alone: the depth where the frusta overlap over ``_FORWARD_OVERLAP`` times
    the rig's spread (a narrower overlap leaves nothing that 90 % of the cameras see)."""
    fwd = np.stack([c.forward for c in cameras]).mean(axis=0)
    norm = float(np.linalg.norm(fwd))
    if norm < 1e-6:
        return None, 0.0
    fwd = fwd / norm
    lateral = (centers - centers.mean(axis=0)) - np.outer((centers - centers.mean(axis=0)) @ fwd, fwd)
    spread = 2.0 * float(np.max(np.linalg.norm(lateral, axis=1)))
    # the narrower half field of view of the rig (pixel extent over focal length)
    tan_half = min(min(0.5 * c.width / c.K[0, 0], 0.5 * c.height / c.K[1, 1]) for c in cameras)
    if spread <= 0 or tan_half <= 0:
        return None, 0.0
    depth = (1.0 + _FORWARD_OVERLAP) * spread / (2.0 * tan_half)
    if images is not None:
        measured = _stereo_depth(cameras, images, centers.mean(axis=0), fwd, depth, tan_half)
        depth = measured if measured is not None else depth
    return centers.mean(axis=0) + depth * fwd, 0.5 * depth


def _stereo_depth(cameras, images, origin: np.ndarray, fwd: np.ndarray, guess: float,
                  tan_half: float) -> float | None:
    """Median depth along ``fwd`` from ``origin`` (world units) of the stereo-confirmed points
    (:func:`wtopo.geometry.mvs.plane_sweep_points`) within ``_STEREO_CENTRAL`` of the half field of view
    ``tan_half`` around the rig's axis; ``None`` when fewer than 8 (an untextured capture) or the views
    differ in size. The sweep runs on ``_STEREO_VIEWS`` views at ``_STEREO_PIXELS`` px in a frame
    centred on ``origin`` and scaled by ``guess`` (the estimate does not depend on the input's units or
    position), over depths from ``_STEREO_NEAR`` to ``_STEREO_FAR`` times ``guess``."""
    import torch
    import torch.nn.functional as fn

    from .mvs import plane_sweep_points

    img = torch.as_tensor(images, dtype=torch.float32)
    if img.ndim != 4 or img.shape[0] != len(cameras) or len({(c.width, c.height) for c in cameras}) != 1:
        return None
    n = min(_STEREO_VIEWS, len(cameras))
    pick = np.unique(np.round(np.linspace(0, len(cameras) - 1, n)).astype(np.int64))
    factor = min(1.0, _STEREO_PIXELS / max(cameras[0].width, cameras[0].height))
    cams = [cameras[i].transformed(1.0 / guess, -origin).scaled(factor) for i in pick]
    small = img[torch.as_tensor(pick)].permute(0, 3, 1, 2)
    small = fn.interpolate(small, size=(cams[0].height, cams[0].width), mode="area").permute(0, 2, 3, 1)
    reach = np.full(3, _STEREO_FAR)
    pts = plane_sweep_points(cams, small, -reach, reach, near=_STEREO_NEAR).points
    z = pts @ fwd
    off = np.linalg.norm(pts - np.outer(z, fwd), axis=1)
    central = (z > 0) & (off <= _STEREO_CENTRAL * tan_half * z)
    if int(central.sum()) < 8:
        return None
    return float(np.median(z[central])) * guess


def visual_hull_box(cameras, masks, images=None) -> tuple[np.ndarray, np.ndarray]:
    """The box ``(lower [3], upper [3])`` (float64, world units) around the visual hull of ``masks``
    (bool [N, H, W] tensor), or for ``masks=None`` around the region 90 % of the frusta hold: carved on a
    sphere around the point the viewing rays converge on, then on the box of the first pass. For
    parallel viewing rays (a forward-facing rig) the sphere lies at the depth the middle of the
    ``images`` (float [N, H, W, 3], optional) shows, by stereo (:func:`_forward_focus`).

    Raises:
        ValueError: the cameras are degenerate (:func:`_check_camera_spread`), a mask is empty, the
            rays are parallel (with masks), or nothing survives the carving.
    """
    centers = np.stack([c.center for c in cameras])
    _check_camera_spread(centers, float(np.max(np.abs(centers))))
    masks_np = None
    if masks is not None:
        masks_np = masks.detach().cpu().numpy().astype(bool)
        if not masks_np.any(axis=(1, 2)).all():
            i = int(np.argmin(masks_np.any(axis=(1, 2))))
            raise ValueError(f"masks[{i}] is empty; every image with a mask must show the object")
        # rays through each mask's centroid converge on the object even for parallel optical axes
        dirs = []
        for cam, m in zip(cameras, masks_np):
            r, c = np.nonzero(m)
            dirs.append(_pixel_ray_world(cam, c.mean() + 0.5, r.mean() + 0.5))
        focus = _converge_point(centers, np.stack(dirs))
    else:
        focus = _converge_point(centers, np.stack([c.forward for c in cameras]))
    radius = None
    if focus is None and masks_np is None:
        focus, radius = _forward_focus(cameras, centers, images)
    if focus is None:
        raise ValueError("the cameras' viewing rays are parallel, so the region of interest cannot be "
                         "estimated from them; give Scene(bounds=...) or init points")
    if radius is None:
        radius = float(np.median(np.linalg.norm(centers - focus, axis=1)))
    lo, hi = focus - radius, focus + radius
    mask_dist = None if masks_np is None else mask_distances(masks_np)
    # a footprint-carved cell may hold the object anywhere in it: half a cell around the kept centres holds
    # all of it; the frustum test samples centres only, so 1.5 cells there
    pad = 0.5 if masks_np is not None else 1.5
    for res in _HULL_GRID:
        kept = carve(cameras, masks_np, lo, hi, res, mask_dist=mask_dist)
        if len(kept) == 0:
            what = "visual hull of the masks" if masks_np is not None else "intersection of the camera frusta"
            raise ValueError(f"the {what} is empty around {focus.tolist()} (radius {radius:.6g}); "
                             "give Scene(bounds=...)")
        cell = (hi - lo) / res
        lo, hi = kept.min(axis=0) - pad * cell, kept.max(axis=0) + pad * cell
    return lo, hi


def points_box(cameras, points: np.ndarray):
    """The 2nd-98th percentile box of the ``points`` [P, 3] that half of the cameras see, grown by 5 %
    of its longest side: ``(lower [3], upper [3])`` float64, or None when fewer than 8 are seen."""
    vis = points[_seen_count(cameras, points) >= math.ceil(0.5 * len(cameras))]
    if len(vis) < 8:
        return None
    lo, hi = np.percentile(vis, 2, axis=0), np.percentile(vis, 98, axis=0)
    pad = 0.05 * (hi - lo).max()
    if pad <= 0:
        return None
    return lo - pad, hi + pad
