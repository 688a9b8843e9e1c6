# SPDX-License-Identifier: Apache-2.0
"""Background of unmasked captures: surfels outside the region of interest, kept at distance.

Without masks every pixel is explained by some surfel. If the only surfels are those in the
region of interest, the photometric loss pulls them towards the cameras to paint the background
(a wall in front of the lens, a closed blob around the cameras). Here the background gets its own
surfels from the start, at the distances it plausibly has, and keeps them there:

* **Initialisation on shells.** Surfels are placed along random pixel rays of random training
  views where the ray crosses spheres around the region of interest whose radii grow
  geometrically from just beyond the farthest camera to ``_FAR_MULTIPLE`` times that (the last
  shell stands in for the sky). A surfel takes the colour of the pixel it came from and a size of
  ``_FOOTPRINT_PIXELS`` pixel footprints at its depth, facing the camera that placed it.
  Only pixels the initial stereo did not explain seed a shell: a pixel within ``_COVER_PIXELS``
  of a confirmed stereo point's projection in its view is left to that point (on DTU, shells
  seeded on the near table's pixels showed its white through the black backdrop of a held-out
  view; ``design/decisions.md``, "background shells").
* **Only for a far scene.** A shell stands for texture the stereo saw but could not place inside the
  region's depth range. When more than ``UNTEXTURED_SHARE`` of the pixels it left unexplained are
  untextured (the sweep's own window test: they have no depth to find), they are near surfaces of
  unknown depth and a backdrop, not a far scene, and no shells are seeded, nor when nothing is left
  unexplained (:func:`shells_wanted`;
  DTU scan24: 85 % untextured, a white table and a black backdrop; the unbounded test scenes
  0-21 %).
* **Contracted steps.** Adam moves every mean by about the learning rate per step whatever the
  gradient's size; a background surfel at distance ``r`` from the region's centre gets its step
  scaled by ``r / R`` (``R``: the region's radius), the Jacobian of the inverse of the
  Mip-NeRF 360 contraction ``x / |x| (2 - 1 / |x|)`` up to a constant: a step in contracted space is
  a step proportional to distance in world space. Surfels in the region of interest move as before.
* **Camera clearance.** Surfels whose centre comes within the layout's ``near`` distance of a
  camera centre are pruned at every density-control step: nothing may sit on the lens.

References:
    Barron et al., Mip-NeRF 360 (CVPR 2022), scene contraction; Huang et al., 2DGS (SIGGRAPH 2024)
    and Yu et al., Gaussian Opacity Fields (2024), unbounded-scene meshing in a region of interest.
"""

from __future__ import annotations

import numpy as np
import torch

from .scene_kind import SceneLayout
from .surfels import Surfels

__all__ = ["shell_radii", "uncovered_pixels", "shells_wanted", "background_surfels", "contract_steps",
           "prune_near_cameras", "BackgroundState"]

_SHELLS = 4  # shells between the first radius and the sky
_FIRST_SHELL = 1.2  # first shell radius, times the farthest camera's distance from the region's centre
_FAR_MULTIPLE = 30.0  # the last shell (the sky) at this multiple of the first radius
_FOOTPRINT_PIXELS = 2.0  # initial surfel radius in pixel footprints at its depth (neighbours overlap)
_MAX_STEP_SCALE = 100.0  # step scaling cap: beyond it a surfel is effectively at infinity
_ROI_GROWTH = 0.1  # "inside the region of interest" allows this fraction of its side around it
_COVER_PIXELS = 2  # a confirmed stereo point explains the pixels within this many pixels of its projection
_COVER_MAX_POINTS = 2_000_000  # more stereo points than this: a random subset marks the covered pixels
UNTEXTURED_SHARE = 0.5  # no shells when more than this share of the stereo's unexplained pixels is untextured


def shell_radii(layout: SceneLayout) -> np.ndarray:
    """Radii [K] of the background shells around the region of interest's centre, internal units."""
    d = np.linalg.norm(layout.camera_centers - layout.roi_center, axis=1)
    first = _FIRST_SHELL * max(float(d.max()), 2.0 * layout.roi_radius)
    return first * _FAR_MULTIPLE ** (np.arange(_SHELLS) / (_SHELLS - 1))


def uncovered_pixels(cameras, points, device: torch.device | str = "cpu",
                     generator: torch.Generator | None = None) -> list[torch.Tensor]:
    """Per view, the pixels no point of ``points`` explains.

    Args:
        cameras: the training views (:class:`~wtopo.camera.Camera`, internal frame).
        points: float [P, 3] points in the same frame (the stereo's confirmed points); more than
            ``_COVER_MAX_POINTS`` are subsampled (``generator`` picks them).
        device: where the projection runs (the fit's device).
        generator: CPU generator for the subsample.

    Returns:
        One bool tensor [H, W] per camera on ``device``: True where no point in front of the camera
        projects within ``_COVER_PIXELS`` pixels (a square window) of the pixel.
    """
    from ..geometry.mvs import TorchCam

    dev = torch.device(device)
    pts = torch.as_tensor(np.asarray(points, np.float64).reshape(-1, 3), dtype=torch.float32)
    if len(pts) > _COVER_MAX_POINTS:
        pts = pts[torch.randperm(len(pts), generator=generator)[:_COVER_MAX_POINTS]]
    pts = pts.to(dev)
    k = 2 * _COVER_PIXELS + 1
    out = []
    with torch.no_grad():
        for cam in cameras:
            u, v, z = TorchCam(cam, dev).project(pts)
            x, y = torch.floor(u), torch.floor(v)
            ok = (z > 0) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
            hit = torch.zeros(cam.height * cam.width, device=dev)
            hit[(y[ok] * cam.width + x[ok]).long()] = 1.0
            cov = torch.nn.functional.max_pool2d(hit.view(1, 1, cam.height, cam.width), k, stride=1,
                                                 padding=_COVER_PIXELS)
            out.append(cov[0, 0] == 0)
    return out


def shells_wanted(images, free: list[torch.Tensor]) -> tuple[bool, float | None]:
    """Whether the pixels the stereo left unexplained call for background shells, and the untextured share of them.

    Args:
        images: the training views' RGB images, each [H, W, 3] in [0, 1] (a [V, H, W, 3] tensor or a list).
        free: :func:`uncovered_pixels` of those views, bool [H, W] each (any device: moved to the images').

    Returns:
        ``(wanted, share)``: ``share`` of the free pixels whose window is untextured
        (:func:`wtopo.geometry.mvs.untextured`, the sweep's window and threshold), ``wanted`` while it is at most
        :data:`UNTEXTURED_SHARE`; ``(False, None)`` when the stereo left no pixel unexplained.
    """
    from ..geometry.mvs import untextured

    counts = []
    with torch.no_grad():
        for img, f in zip(images, free):
            f = f.to(img.device)
            counts.append(torch.stack([(untextured(img) & f).sum(), f.sum()]))
    flat, total = torch.stack(counts).sum(0).tolist() if counts else (0, 0)  # one host read for every view
    if not total:
        return False, None
    share = flat / total
    return share <= UNTEXTURED_SHARE, share


def background_surfels(scene, layout: SceneLayout, n: int, *, sh_degree: int, opacity: float,
                       device: torch.device, generator: torch.Generator,
                       free: list[torch.Tensor] | None = None) -> Surfels | None:
    """``n`` background surfels on the shells of :func:`shell_radii`, seen from ``scene``'s views.

    Args:
        scene: the training views, internal frame.
        layout: region of interest and camera layout.
        n: surfels to create (split evenly over the shells); ``0`` gives ``None``.
        sh_degree: SH degree of the new surfels.
        opacity: initial opacity in (0, 1).
        device: torch device of the result.
        generator: seeds the views, pixels and shells (CPU generator).
        free: the pixels seeds may come from, bool [H, W] per view (:func:`uncovered_pixels` of the stereo's
            confirmed points); every pixel when ``None`` or when none is free.

    Returns:
        :class:`Surfels` (internal frame) or ``None``.
    """
    if n <= 0:
        return None
    radii = shell_radii(layout)
    c = layout.roi_center
    cams = scene.cameras
    if free is not None:
        free = [f.cpu().numpy() for f in free]
        if not any(f.any() for f in free):
            free = None
    if free is None:
        free = [np.ones((cam.height, cam.width), bool) for cam in cams]
    counts = torch.as_tensor([float(f.sum()) for f in free], dtype=torch.float64)
    view = torch.multinomial(counts, n, replacement=True, generator=generator).numpy()  # views by free pixels
    pick = torch.rand(n, generator=generator, dtype=torch.float64).numpy()
    shell = np.arange(n) % len(radii)
    pts = np.zeros((n, 3))
    cols = np.zeros((n, 3))
    nrm = np.zeros((n, 3))
    scale = np.zeros(n)
    for i in np.unique(view):
        sel = np.nonzero(view == i)[0]
        cam = cams[i]
        flat = np.flatnonzero(free[i])
        r_i, c_i = np.divmod(flat[np.minimum((pick[sel] * len(flat)).astype(np.int64), len(flat) - 1)], cam.width)
        d = cam.pixel_directions_camera(r_i, c_i) @ cam.R  # world directions of these pixels alone
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        o = cam.center
        # far root of |o + t d - c| = r: every shell lies beyond every camera, so it exists and t > 0
        oc = o - c
        b = d @ oc
        r = radii[shell[sel]]
        t = -b + np.sqrt(np.maximum(b * b - (oc @ oc - r * r), 0.0))
        pts[sel] = o + t[:, None] * d
        cols[sel] = scene.images[i][torch.as_tensor(r_i).to(scene.images.device),
                                    torch.as_tensor(c_i).to(scene.images.device)].detach().double().cpu().numpy()
        nrm[sel] = -d
        # pixel footprint at distance t along the ray: t / f
        scale[sel] = _FOOTPRINT_PIXELS * t / float(cam.K[0, 0])
    tt = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    return Surfels.from_points(tt(pts), tt(cols), scales=tt(scale), normals=tt(nrm), opacity=opacity,
                               sh_degree=sh_degree, generator=generator)


class BackgroundState:
    """What the fit needs of the layout at every step, on the fit's device.

    Args:
        layout: region of interest and cameras (internal frame).
        device: torch device.
    """

    def __init__(self, layout: SceneLayout, device: torch.device):
        self.layout = layout
        self.center = torch.as_tensor(layout.roi_center, dtype=torch.float32, device=device)
        self.radius = float(layout.roi_radius)
        self.cameras = torch.as_tensor(layout.camera_centers, dtype=torch.float32, device=device)
        self.near = float(layout.near)

    def step_scale(self, means: torch.Tensor) -> torch.Tensor:
        """Per-surfel step multiplier [N]: 1 inside the region's sphere, ``r / R`` outside."""
        r = torch.linalg.norm(means.detach() - self.center, dim=-1) / self.radius
        return r.clamp(1.0, _MAX_STEP_SCALE)

    def outside_roi(self, means: torch.Tensor) -> torch.Tensor:
        """Boolean [N]: the surfel centre lies outside the region of interest (grown by ``_ROI_GROWTH``)."""
        side = float(np.max(self.layout.roi_upper - self.layout.roi_lower))
        lo = torch.as_tensor(self.layout.roi_lower - _ROI_GROWTH * side, dtype=means.dtype, device=means.device)
        hi = torch.as_tensor(self.layout.roi_upper + _ROI_GROWTH * side, dtype=means.dtype, device=means.device)
        m = means.detach()
        return ~((m >= lo) & (m <= hi)).all(dim=-1)

    def near_cameras(self, means: torch.Tensor) -> torch.Tensor:
        """Boolean [N]: the surfel centre lies within ``near`` of some camera centre."""
        d = torch.cdist(means.detach(), self.cameras)
        return (d < self.near).any(dim=1)


def contract_steps(means: torch.Tensor, before: torch.Tensor, scale: torch.Tensor) -> None:
    """Rescale the optimiser's last step of ``means`` (in place): ``before + scale * (means - before)``.

    Args:
        means: the mean parameter after ``optimizer.step()`` [N, 3].
        before: the means before the step [N, 3] (same N: call before any density change).
        scale: per-surfel multiplier [N] (:meth:`BackgroundState.step_scale` of ``before``).
    """
    with torch.no_grad():
        means.copy_(before + scale[:, None] * (means - before))


def prune_near_cameras(surfels: Surfels, state: BackgroundState) -> int:
    """Remove the surfels within ``near`` of a camera centre (one host read); returns how many went (none when that
    would be every surfel)."""
    near = state.near_cameras(surfels.means)
    k = int(near.sum())
    if k in (0, len(surfels)):
        return 0
    surfels.prune(~near)
    return k
