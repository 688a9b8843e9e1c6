# SPDX-License-Identifier: Apache-2.0
"""Plane-sweep multi-view stereo: initial points for captures that come without any.

A capture with cameras but no sparse points (DTU, a synthetic rig, a ``transforms.json`` without
its point cloud) used to start from random points in the cameras' common volume, which a few
hundred CPU iterations cannot pull onto a textured scene. This module gives every training view a
depth map by sweeping depth hypotheses through its region-of-interest depth range and scoring each
by normalised cross-correlation (NCC) of a window against its neighbouring views, keeps the depths
that the neighbours' own depth maps confirm (forward-backward reprojection), and returns the
confirmed pixels as coloured, oriented points.

* Neighbours: per reference view, the ``_NEIGHBOURS`` views whose triangulation angle at the
  region of interest's centre is best scored (a Gaussian around ``_BEST_ANGLE``, wider above it)
  among those that look the same way (optical axes within 75 degrees).
* Hypotheses: two plane families (multi-direction plane sweep). Planes facing the reference camera,
  uniform in inverse depth between the nearest and farthest corner of the region of interest seen
  from it (never nearer than the scene's near distance), about one plane per pixel of epipolar
  travel in the best neighbour (``_MIN_PLANES`` to ``_MAX_PLANES``); and, when the cameras agree on
  an up direction, level planes across it spanning the region's height: a ground or table seen at
  a grazing angle is foreshortened too much for a camera-facing window to match, a level plane
  warps it exactly. Each pixel keeps the family that matches best; a level winner takes the up
  direction as its normal.
* Warping uses the cameras' own projection (distortion and skew), so no undistortion is needed.
* Score: per hypothesis the mean of the best half of the neighbours' NCCs (robust to a neighbour
  that is occluded there); untextured windows (sky, flat paint) get no depth. The winner's depth is
  refined by a parabola through its neighbouring hypotheses.
* Filter: a depth is kept when at least ``_MIN_CONSISTENT`` neighbours' depths reproject to within
  ``_REPROJ_PIXELS`` px and ``_DEPTH_REL`` relative depth of it.

The score of every hypothesis is :func:`wtopo.plane_sweep.plane_costs` (Warp kernels); the rest is torch. Both run
on the fit's device (CPU or CUDA); nothing here is differentiated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .._profile import section
from ..camera import Camera
from ..multiview_ncc import source_params
from ..plane_sweep import LevelPlanes, SweepReference, plane_costs

__all__ = ["MVSPoints", "TorchCam", "TorchCams", "confirmed_points", "gray", "plane_sweep_points", "select_neighbours",
           "untextured"]

_NEIGHBOURS = 4  # source views per reference view
_BEST_ANGLE = 12.0  # degrees: preferred triangulation angle at the region of interest
_ANGLE_SIGMA_BELOW = 4.0  # degrees: score falls off this fast below the preferred angle ...
_ANGLE_SIGMA_ABOVE = 15.0  # ... and this fast above it (wide baselines still triangulate)
_MAX_AXIS_ANGLE = 75.0  # degrees: a neighbour must look within this of the reference's direction
_UP_AGREEMENT = 0.7  # the cameras' up axes must agree this much for a level-plane sweep
_WINDOW = 7  # NCC window side, pixels
_MIN_TEXTURE = 1e-4  # window variance (grey levels in [0, 1]) below this has no depth
_MIN_SCORE = 0.5  # aggregated NCC a winning hypothesis needs
_MIN_PLANES, _MAX_PLANES = 48, 192
_REPROJ_PIXELS = 1.0  # forward-backward reprojection tolerance, pixels
_DEPTH_REL = 0.01  # relative depth tolerance of the forward-backward check
_MIN_CONSISTENT = 2  # neighbours that must confirm a depth (fewer when a view has fewer neighbours)
_NORMAL_STEP = 2  # pixels between the depth samples a normal is taken from (1 is noisy at sub-pixel depth noise)


@dataclass
class MVSPoints:
    """Confirmed plane-sweep points in the cameras' frame.

    Attributes:
        points: float64 [P, 3] positions (the cameras' units).
        colors: float64 [P, 3] RGB in [0, 1] of the reference pixel.
        normals: float64 [P, 3] unit normals facing the reference camera (from the depth map).
        view_fraction: float, fraction of the views' pixels that kept a depth (a diagnostic).
    """

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    view_fraction: float


def capture_up(cameras: list[Camera]) -> np.ndarray | None:
    """The capture's up direction [3]: the mean of the cameras' image-up axes when they agree (mean
    length >= ``_UP_AGREEMENT``: phones held upright, orbits, rigs), else ``None``."""
    ups = np.stack([-cam.R[1] for cam in cameras])  # OpenCV: image y points down
    m = ups.mean(0)
    n = float(np.linalg.norm(m))
    return m / n if n >= _UP_AGREEMENT else None


def select_neighbours(cameras: list[Camera], center: np.ndarray, k: int = _NEIGHBOURS) -> list[list[int]]:
    """For each camera, up to ``k`` neighbour indices, best first (see the module docstring).

    Args:
        cameras: the views.
        center: [3] the region of interest's centre, the cameras' units.
        k: neighbours per view.
    """
    c = np.stack([cam.center for cam in cameras])
    fwd = np.stack([cam.forward for cam in cameras])
    to_c = c - np.asarray(center, np.float64)[None]
    to_c /= np.maximum(np.linalg.norm(to_c, axis=1, keepdims=True), 1e-12)
    tri = np.degrees(np.arccos(np.clip(to_c @ to_c.T, -1.0, 1.0)))
    axis = np.degrees(np.arccos(np.clip(fwd @ fwd.T, -1.0, 1.0)))
    sigma = np.where(tri < _BEST_ANGLE, _ANGLE_SIGMA_BELOW, _ANGLE_SIGMA_ABOVE)
    score = np.exp(-0.5 * ((tri - _BEST_ANGLE) / sigma) ** 2)
    # parallel rigs (forward-facing): the angle at the centre is small; baseline still separates them
    dist = np.linalg.norm(c[:, None] - c[None], axis=-1)
    score = np.where((axis <= _MAX_AXIS_ANGLE) & (dist > 1e-9), score, -1.0)
    np.fill_diagonal(score, -1.0)
    out = []
    for i in range(len(cameras)):
        order = np.argsort(-score[i], kind="stable")
        out.append([int(j) for j in order[:k] if score[i, j] > 0])
    return out


class TorchCam:
    """A camera's projection and rays as torch tensors on one device (float32 unless ``dtype`` says)."""

    def __init__(self, cam: Camera, device: torch.device, dtype: torch.dtype = torch.float32):
        self.cam = cam
        kw = dict(dtype=dtype, device=device)
        self.R = torch.as_tensor(cam.R, **kw)
        self.t = torch.as_tensor(cam.t, **kw)
        self.K = torch.as_tensor(cam.K, **kw)
        self.dist = None if cam.distortion is None else [float(x) for x in cam.distortion]
        self._device, self._dtype = device, dtype
        self.W, self.H = cam.width, cam.height

    @property
    def origin(self) -> torch.Tensor:
        """Every pixel ray's origin [H, W, 3] (built on first use; a projection alone never needs it)."""
        return self.cam.pixel_rays(self._device, self._dtype)[0]

    @property
    def dirs(self) -> torch.Tensor:
        """Every pixel ray's direction [H, W, 3], camera z = 1 (built on first use, cached on the camera)."""
        return self.cam.pixel_rays(self._device, self._dtype)[1]

    def project(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points [..., 3] -> pixel u, v (continuous, centres at +0.5) and z-depth."""
        return self.project_camera(x @ self.R.T + self.t)

    def project_camera(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points in this camera's frame [..., 3] -> pixel u, v (continuous, centres at +0.5) and z-depth."""
        z = p[..., 2]
        zs = torch.where(z.abs() < 1e-12, 1e-12, z)
        xn, yn = p[..., 0] / zs, p[..., 1] / zs
        if self.dist is not None:
            k1, k2, p1, p2, k3 = self.dist
            r2 = xn * xn + yn * yn
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xn, yn = (xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn),
                      yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn)
        u = self.K[0, 0] * xn + self.K[0, 1] * yn + self.K[0, 2]
        v = self.K[1, 1] * yn + self.K[1, 2]
        return u, v, z

    def grid(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates -> ``grid_sample`` coordinates (align_corners=False)."""
        return torch.stack([u / self.W * 2 - 1, v / self.H * 2 - 1], dim=-1)


class TorchCams:
    """``cameras`` as :class:`TorchCam`, each made once per device and dtype: ``cams(i, device, dtype)``."""

    def __init__(self, cameras: Sequence[Camera]):
        self.cameras = cameras
        self._made: dict[tuple, TorchCam] = {}

    def __call__(self, i: int, device: torch.device, dtype: torch.dtype = torch.float32) -> TorchCam:
        """Camera ``i`` on ``device`` in ``dtype``, made on the first call."""
        c = self._made.get((i, device, dtype))
        if c is None:
            c = self._made[(i, device, dtype)] = TorchCam(self.cameras[i], device, dtype)
        return c


def _box_sum(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Sum over a ``_WINDOW`` run along ``dim`` (zero outside), by a running sum."""
    h = _WINDOW // 2
    pad = [0, 0] * (x.ndim - 1 - (dim % x.ndim)) + [h + 1, h]
    c = torch.cumsum(F.pad(x, pad), dim=dim)
    n = x.shape[dim]
    return c.narrow(dim, _WINDOW, n) - c.narrow(dim, 0, n)


def _box(x: torch.Tensor) -> torch.Tensor:
    """Window mean over the last two dims [..., H, W]; border windows average their in-image pixels.

    Running sums: on the CPU three times faster than ``avg_pool2d`` (separable or not) and ten times faster than a
    separable ``conv2d`` at [160, 1, 192, 192]."""
    ones = torch.ones(x.shape[-2:], dtype=x.dtype, device=x.device)
    count = _box_sum(_box_sum(ones, -1), -2)
    return _box_sum(_box_sum(x, -1), -2) / count


def _depth_range(cam: Camera, lower: np.ndarray, upper: np.ndarray, near: float) -> tuple[float, float]:
    corners = np.array([[(lower, upper)[b >> a & 1][a] for a in range(3)] for b in range(8)])
    z = corners @ cam.R.T[:, 2] + cam.t[2]
    inside = bool(np.all(cam.center >= lower) and np.all(cam.center <= upper))
    lo = near if inside else max(float(z.min()), near)
    hi = max(float(z.max()), 2.0 * lo)
    return lo, hi


def _n_planes(ref: TorchCam, src: TorchCam, lo: float, hi: float) -> int:
    """About one plane per pixel of epipolar travel of the reference's central pixel."""
    o = ref.origin[ref.H // 2, ref.W // 2]
    d = ref.dirs[ref.H // 2, ref.W // 2]
    u, v, z = src.project(torch.stack([o + d * lo, o + d * hi]))
    if bool((z <= 0).any()):
        return _MAX_PLANES
    travel = float(torch.hypot(u[1] - u[0], v[1] - v[0]))
    return int(np.clip(math.ceil(travel), _MIN_PLANES, _MAX_PLANES))


def _window_moments(g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance [H, W] float64 of the ``_WINDOW`` window around each pixel of the grey image ``g`` [H, W]
    (float64: a flat window's variance is a difference of near-equal sums)."""
    r = g.double()[None, None]
    mu = _box(r)[0, 0]
    return mu, (_box(r * r)[0, 0] - mu * mu).clamp_min(0)


def untextured(img: torch.Tensor) -> torch.Tensor:
    """Bool [H, W]: the pixels of ``img`` (RGB [H, W, 3] in [0, 1]) whose window's grey variance is below
    ``_MIN_TEXTURE``, the windows the sweep gives no depth (:func:`_window_moments`, as the sweep's)."""
    return _window_moments(gray(img.double()))[1] < _MIN_TEXTURE


def gray(img: torch.Tensor) -> torch.Tensor:
    """Luma (ITU-R BT.601 weights) of an RGB image [..., 3] -> [...]."""
    return (img @ torch.tensor([0.299, 0.587, 0.114], dtype=img.dtype, device=img.device))


class _Fronto:
    """Planes facing the reference camera, uniform in inverse depth between ``lo`` and ``hi``."""

    def __init__(self, lo: float, hi: float, n: int, device):
        self.params = torch.linspace(1.0 / lo, 1.0 / hi, n, device=device)

    def depth_at(self, p: torch.Tensor) -> torch.Tensor:
        return 1.0 / p.clamp_min(1e-12)


class _Level:
    """Planes across ``up`` (floors, ground, table tops) at heights ``params`` spanning the region of
    interest; a pixel's depth is where its ray meets the plane, kept within ``[lo, hi]``."""

    def __init__(self, ref: TorchCam, up: np.ndarray, heights: tuple[float, float], lo: float, hi: float, n: int):
        u = torch.as_tensor(up, dtype=torch.float32, device=ref.dirs.device)
        self.a = (ref.origin * u).sum(-1)  # [H, W] camera height
        self.b = (ref.dirs * u).sum(-1)  # [H, W] height change per unit depth
        self.params = torch.linspace(heights[0], heights[1], n, device=ref.dirs.device)
        self.lo, self.hi = lo, hi

    def _valid(self, d: torch.Tensor) -> torch.Tensor:
        return torch.where((d >= self.lo) & (d <= self.hi), d, -1.0)

    def depth_at(self, p: torch.Tensor) -> torch.Tensor:
        b = torch.where(self.b.abs() < 1e-6, 1e-6, self.b)
        return self._valid((p - self.a) / b)


def _sweep(ref: TorchCam, srcs: list[TorchCam], ref_gray: torch.Tensor, src_gray: torch.Tensor,
           family: _Fronto | _Level) -> tuple[torch.Tensor, torch.Tensor]:
    """Best depth [H, W] (0: none) and its aggregated NCC [H, W] (-1: none) of one reference view over
    one ``family`` of planes."""
    params = family.params
    n_planes = int(params.shape[0])
    mu_r, var_r = (m.float() for m in _window_moments(ref_gray))
    rows = torch.stack([source_params(ref.cam, src.cam, device=ref_gray.device) for src in srcs])
    planes = params if isinstance(family, _Fronto) else LevelPlanes(params, family.a, family.b, family.lo, family.hi)
    costs = plane_costs(SweepReference(ref_gray, mu_r, var_r, ref.dirs), src_gray, rows, planes, half=_WINDOW // 2,
                        best=max(1, (len(srcs) + 1) // 2), min_texture=_MIN_TEXTURE)
    score, idx = costs.max(0)
    # parabola through the winner and its neighbours, in the family's parameter
    i0 = idx.clamp(1, max(n_planes - 2, 1)) if n_planes >= 3 else idx
    c_m = costs.gather(0, (i0 - 1).clamp_min(0)[None])[0]
    c_0 = costs.gather(0, i0[None])[0]
    c_p = costs.gather(0, (i0 + 1).clamp_max(n_planes - 1)[None])[0]
    den = c_m - 2 * c_0 + c_p
    off = torch.where(den < -1e-9, 0.5 * (c_m - c_p) / den, torch.zeros_like(den)).clamp(-0.5, 0.5)
    off = torch.where(idx == i0, off, torch.zeros_like(off))
    step = params[1] - params[0] if n_planes > 1 else params.new_tensor(0.0)
    depth = family.depth_at(params[idx] + off * step)
    keep = (score > _MIN_SCORE) & (var_r > _MIN_TEXTURE) & (depth > 0)
    return torch.where(keep, depth, 0.0), torch.where(keep, score, -1.0)


def _consistent(ref: TorchCam, depth: torch.Tensor, srcs: list[TorchCam],
                src_depths: list[torch.Tensor]) -> torch.Tensor:
    """Per reference pixel, how many neighbours' depth maps confirm its depth."""
    x = ref.origin + ref.dirs * depth[..., None]
    count = torch.zeros_like(depth, dtype=torch.int32)
    ju, jv = torch.meshgrid(torch.arange(ref.W, device=depth.device) + 0.5,
                            torch.arange(ref.H, device=depth.device) + 0.5, indexing="xy")
    for src, sd in zip(srcs, src_depths):
        u, v, z = src.project(x)
        ui, vi = u.floor().long(), v.floor().long()
        inside = (z > 0) & (ui >= 0) & (ui < src.W) & (vi >= 0) & (vi < src.H)
        ui, vi = ui.clamp(0, src.W - 1), vi.clamp(0, src.H - 1)
        d_s = sd[vi, ui]
        y = src.origin[vi, ui] + src.dirs[vi, ui] * d_s[..., None]
        u2, v2, z2 = ref.project(y)
        ok = (inside & (d_s > 0) & (depth > 0) & (torch.hypot(u2 - ju, v2 - jv) < _REPROJ_PIXELS)
              & ((z2 - depth).abs() < _DEPTH_REL * depth))
        count += ok.int()
    return count


def _normals(ref: TorchCam, depth: torch.Tensor) -> torch.Tensor:
    """Unit normals [H, W, 3] from the depth map's central differences ``_NORMAL_STEP`` pixels
    apart, facing the camera; 0 where one of the four has no depth."""
    x = ref.origin + ref.dirs * depth[..., None]
    n = torch.zeros_like(x)
    k = _NORMAL_STEP
    H, W = depth.shape
    if min(H, W) <= 2 * k:
        return n
    inner = (slice(k, H - k), slice(k, W - k))
    dx = x[k:H - k, 2 * k:] - x[k:H - k, :W - 2 * k]
    dy = x[2 * k:, k:W - k] - x[:H - 2 * k, k:W - k]
    c = torch.cross(dx, dy, dim=-1)
    has = ((depth[k:H - k, 2 * k:] > 0) & (depth[k:H - k, :W - 2 * k] > 0) & (depth[2 * k:, k:W - k] > 0)
           & (depth[:H - 2 * k, k:W - k] > 0))
    c = torch.where(has[..., None], c, torch.zeros_like(c))
    flip = (c * ref.dirs[inner]).sum(-1, keepdim=True) > 0
    c = torch.where(flip, -c, c)
    n[inner] = c / c.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return n


def plane_sweep_points(cameras: list[Camera], images: torch.Tensor, roi_lower: np.ndarray, roi_upper: np.ndarray,
                       *, near: float, device: torch.device | str = "cpu", max_views: int | None = None) -> MVSPoints:
    """Coloured, oriented points from plane-sweep stereo over every view (module docstring).

    Args:
        cameras: the training views (any lens model :class:`wtopo.Camera` supports).
        images: float [N, H, W, 3] RGB in [0, 1], one per camera (sizes may differ only if passed as
            a list).
        roi_lower: [3] lower corner of the region of interest, the cameras' units.
        roi_upper: [3] its upper corner: each view sweeps the depths of the box's corners.
        near: no hypothesis nearer than this to a camera (the cameras' units, > 0).
        device: where the sweep runs (the fit's device).
        max_views: sweep at most this many views, evenly spaced through the list (each still has its
            neighbours among them); ``None``: every view. The points are thinned to the surfel
            budget anyway, so a CPU fit need not pay for every view.

    Returns:
        :class:`MVSPoints` (empty arrays when nothing is confirmed: an untextured capture).
    """
    if len(cameras) < 2:
        raise ValueError(f"plane-sweep stereo needs at least 2 views, got {len(cameras)}")
    if not near > 0:
        raise ValueError(f"near must be > 0, got {near!r}")
    if max_views is not None and (isinstance(max_views, bool) or int(max_views) != max_views or max_views < 2):
        raise ValueError(f"max_views must be an integer >= 2 or None, got {max_views!r}")
    if max_views is not None and len(cameras) > max_views:
        pick = np.unique(np.round(np.linspace(0, len(cameras) - 1, int(max_views))).astype(np.int64))
        cameras = [cameras[i] for i in pick]
        images = [images[i] for i in pick]
    lower, upper = np.asarray(roi_lower, np.float64), np.asarray(roi_upper, np.float64)
    dev = torch.device(device)
    tcams = [TorchCam(c, dev) for c in cameras]
    grays = [gray(torch.as_tensor(images[i], dtype=torch.float32).to(dev)) for i in range(len(cameras))]
    nbrs = select_neighbours(cameras, 0.5 * (lower + upper))
    up = capture_up(cameras)
    corners = np.array([[(lower, upper)[b >> a & 1][a] for a in range(3)] for b in range(8)])
    depths, level = [], []
    with torch.no_grad(), section("stereo_sweep"):
        for i, ref in enumerate(tcams):
            if not nbrs[i]:
                depths.append(torch.zeros(ref.H, ref.W, device=dev))
                level.append(torch.zeros(ref.H, ref.W, dtype=torch.bool, device=dev))
                continue
            srcs = [tcams[j] for j in nbrs[i]]
            if any((s.H, s.W) != (ref.H, ref.W) for s in srcs):
                raise ValueError("plane-sweep stereo needs views of one size; resize the images first")
            lo, hi = _depth_range(cameras[i], lower, upper, near)
            n_planes = _n_planes(ref, srcs[0], lo, hi)
            src_gray = torch.stack([grays[j] for j in nbrs[i]])
            d, score = _sweep(ref, srcs, grays[i], src_gray, _Fronto(lo, hi, n_planes, dev))
            won = torch.zeros_like(d, dtype=torch.bool)
            if up is not None:
                h = corners @ up
                d2, score2 = _sweep(ref, srcs, grays[i], src_gray,
                                    _Level(ref, up, (float(h.min()), float(h.max())), lo, hi, n_planes))
                won = score2 > score
                d = torch.where(won, d2, d)
            depths.append(d)
            level.append(won & (d > 0))
    with section("stereo_confirm"):
        return confirmed_points(tcams, images, nbrs, depths, level, up)


def confirmed_points(tcams: list[TorchCam], images, nbrs: list[list[int]], depths: list[torch.Tensor],
                     level: list[torch.Tensor], up: np.ndarray | None) -> MVSPoints:
    """The sweep's second half: the depths [H, W] per view (0: none) that the neighbours ``nbrs`` confirm
    (forward-backward check), as coloured points with normals from the depth map (a level-plane winner, ``level``
    [H, W] bool, takes the ``up`` direction facing its camera). ``images``: RGB [H, W, 3] per view."""
    dev = depths[0].device
    with torch.no_grad():
        pts, cols, nrms = [], [], []
        kept = total = 0
        for i, ref in enumerate(tcams):
            if not nbrs[i]:
                continue
            need = min(_MIN_CONSISTENT, len(nbrs[i]))
            n_ok = _consistent(ref, depths[i], [tcams[j] for j in nbrs[i]], [depths[j] for j in nbrs[i]])
            nrm = _normals(ref, depths[i])
            if up is not None:  # a level plane's winners take its normal, facing the camera
                u = torch.as_tensor(up, dtype=torch.float32, device=dev).expand_as(nrm)
                u = torch.where(((ref.dirs * u).sum(-1, keepdim=True) > 0), -u, u)
                nrm = torch.where(level[i][..., None], u, nrm)
            good = (n_ok >= need) & (depths[i] > 0) & (nrm.norm(dim=-1) > 0)
            total += good.numel()
            kept += int(good.sum())
            x = ref.origin + ref.dirs * depths[i][..., None]
            pts.append(x[good].double().cpu().numpy())
            cols.append(torch.as_tensor(images[i], dtype=torch.float32).to(dev)[good].double().cpu().numpy())
            nrms.append(nrm[good].double().cpu().numpy())
    if not pts:
        z = np.zeros((0, 3))
        return MVSPoints(z, z.copy(), z.copy(), 0.0)
    return MVSPoints(np.concatenate(pts), np.concatenate(cols), np.concatenate(nrms), kept / max(total, 1))
