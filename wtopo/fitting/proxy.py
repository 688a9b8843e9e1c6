# SPDX-License-Identifier: Apache-2.0
"""The differentiable proxy mesh: oriented points -> Poisson indicator -> marching cubes -> ray cast.

:class:`ProxyMesh` keeps what is worth keeping between iterations (the BVH of the ray caster,
refitted when only vertex positions change) and returns ``None`` when a surfel state yields no
surface, so the caller skips the mesh losses for that iteration instead of ray casting nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from .._profile import section
from ..raycast import MeshRaycaster, MeshRender
from .config import MeshConfig
from .surfels import Surfels

__all__ = ["ProxyMesh", "ProxyResult", "poisson_mesh", "region_clip", "PADDING"]

PADDING = 0.1
"""Poisson domain padding, fraction of the unit cube on each side (keeps the surface off the periodic wrap)."""
_OFFSET = 0.5  # tangent offset of a surfel's 4 extra oriented points, in surfel sigmas
_OFFSET_WEIGHT = 0.5  # weight of the extra points relative to the centre

_BOX_GROWTH = 0.1  # "initial_mesh" Poisson box: the TSDF mesh's box grown by 10 % (public code)
_EXIT_STEP_CELLS = 1e-3  # the exit ray starts this many grid cells past the entry hit
_CLIP_INPUT_CELLS = 2.0  # with a clip box, the Poisson input is the points within this many cells of it


def poisson_mesh(points: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor, resolution: int, *,
                 sigma: float, padding: float, level_sigma: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Zero level set of the Poisson indicator of oriented points in ``[0, 1]^3``.

    Returns ``(verts [V, 3], faces [F, 3] int32)`` in the points' frame, differentiable w.r.t. the
    points, normals and weights; ``F = 0`` when the field has no zero crossing. ``level_sigma``: the
    local level's Gaussian in grid cells (0: one global level), see :func:`wtopo.poisson.poisson_indicator`.
    """
    from ..marching_cubes import marching_cubes
    from ..poisson import poisson_indicator

    with section("poisson"):
        field = poisson_indicator(points, normals, weights, int(resolution), sigma=sigma, padding=padding,
                                  level_sigma=level_sigma)
    with section("marching_cubes"):
        return marching_cubes(field.chi, 0.0, lower=field.lower, upper=field.upper)


def region_clip(cfg: MeshConfig, layout) -> tuple[np.ndarray, np.ndarray] | None:
    """The :class:`ProxyMesh` ``clip`` box for ``cfg``: the region of interest ``(roi_lower, roi_upper)`` of
    ``layout`` (a :class:`~wtopo.fitting.scene_kind.SceneLayout`) when ``cfg.clip_to_region``, else ``None``."""
    return (layout.roi_lower, layout.roi_upper) if cfg.clip_to_region and layout is not None else None


@dataclass
class ProxyResult:
    """One proxy mesh.

    Attributes:
        verts: vertices [V, 3] in the internal frame, differentiable w.r.t. the surfel parameters.
        faces: int32 [F, 3], discrete.
    """

    verts: torch.Tensor
    faces: torch.Tensor

    @property
    def num_faces(self) -> int:
        """Number of faces F."""
        return int(self.faces.shape[0])


class ProxyMesh:
    """Builds the proxy mesh from surfels and renders it.

    Args:
        cfg: proxy mesh settings.
        box: ``(lower [3], upper [3])`` of the Poisson domain in the internal frame; ``None`` for
            the unit cube.
        prior: optional ``(points [P, 3], normals [P, 3])`` splatted into the Poisson input with
            weight ``cfg.surface_prior`` (the public TopoSurfel code's surface prior).
        clip: optional ``(lower [3], upper [3])`` in the internal frame (a scene's region of interest):
            :meth:`build` takes the oriented points within two Poisson cells of it (a scene's background
            surfels, never oriented by a mesh, stay out of the solve) and drops the faces whose centroid
            lies farther than one cell outside it.
            Outside the region the proxy of an open scene is the Poisson solve's own closing: the
            periodic image of a ground the region cuts, halfway to its copy across the domain's wrap,
            lies over the region and would hide it from the cameras.
    """

    def __init__(self, cfg: MeshConfig, *, box: tuple[np.ndarray, np.ndarray] | None = None,
                 prior: tuple[torch.Tensor, torch.Tensor] | None = None,
                 clip: tuple[np.ndarray, np.ndarray] | None = None):
        self.cfg = cfg
        self.clip = None if clip is None else (np.asarray(clip[0], np.float64), np.asarray(clip[1], np.float64))
        self.raycaster = MeshRaycaster()
        self.box = box
        if box is None:
            self.lower, self.size = np.zeros(3), 1.0
        else:
            lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
            side = float(np.max(hi - lo)) * (1 + 2 * _BOX_GROWTH)
            self.lower, self.size = 0.5 * (lo + hi) - 0.5 * side, side
        self.prior = prior

    def with_resolution(self, resolution: int) -> ProxyMesh:
        """This proxy on a grid of ``resolution`` nodes per side: the same box, prior and settings."""
        return ProxyMesh(replace(self.cfg, resolution=int(resolution)), box=self.box, prior=self.prior, clip=self.clip)

    @property
    def cell(self) -> float:
        """Edge of one Poisson grid cell in the fit's internal frame (``cfg.resolution`` must be set)."""
        if self.cfg.resolution is None:
            raise ValueError("mesh.resolution is None: pass the configuration resolved by the plan")
        return self.size / int(self.cfg.resolution)

    def _to_box(self, p: torch.Tensor) -> torch.Tensor:
        return (p - torch.as_tensor(self.lower, dtype=p.dtype, device=p.device)) / self.size

    def _from_box(self, p: torch.Tensor) -> torch.Tensor:
        return p * self.size + torch.as_tensor(self.lower, dtype=p.dtype, device=p.device)

    def build(self, surfels: Surfels) -> ProxyResult | None:
        """The proxy mesh of the current surfels (``None`` when it has no faces).

        Differentiable w.r.t. the surfel means, rotations, scales and opacities. With a ``clip`` box only
        the faces within a cell of it are kept (the vertices stay).
        """
        from ..oriented_points import oriented_points

        c = self.cfg
        with section("oriented_points"):
            op = oriented_points(surfels.means, surfels.quats, surfels.scales, surfels.opacities,
                                 samples=int(c.samples_per_surfel), offset=_OFFSET, opacity_threshold=0.0,
                                 center_weight=1.0, offset_weight=_OFFSET_WEIGHT,
                                 normal_sign=surfels.buffers["normal_sign"])
        pts, nrm, w = self._to_box(op.points), op.normals, op.weights
        if self.prior is not None and c.surface_prior > 0:
            pp, pn = self.prior
            pts = torch.cat([pts, self._to_box(pp.to(pts))])
            nrm = torch.cat([nrm, pn.to(nrm)])
            w = torch.cat([w, torch.full((pp.shape[0],), float(c.surface_prior), dtype=w.dtype, device=w.device)])
        # points outside the Poisson domain (with a clip box: outside it, grown by _CLIP_INPUT_CELLS) carry
        # no weight (their gradient is exactly 0)
        inside = ((pts >= 0) & (pts <= 1)).all(dim=-1)
        if self.clip is not None:
            lo, hi = self._clip_bounds(_CLIP_INPUT_CELLS, pts, box_frame=True)
            inside = inside & ((pts >= lo) & (pts <= hi)).all(dim=-1)
        w = torch.where(inside, w, torch.zeros_like(w))
        pts = torch.where(inside[:, None], pts, torch.full_like(pts, 0.5))
        if not bool((w > 0).any()):  # host sync: one per iteration, decides whether a mesh exists
            return None
        verts, faces = poisson_mesh(pts, nrm, w, int(c.resolution), sigma=c.sigma, padding=PADDING,
                                    level_sigma=float(c.level_sigma or 0.0))
        if faces.shape[0] == 0:
            return None
        verts = self._from_box(verts)
        if self.clip is not None:
            faces = self._clipped(verts, faces)
            if faces.shape[0] == 0:
                return None
        return ProxyResult(verts, faces)

    def _clip_bounds(self, cells: float, like: torch.Tensor, *, box_frame: bool = False):
        """``(lower [3], upper [3])`` of the ``clip`` box grown by ``cells`` Poisson cells, as tensors like
        ``like``: in the internal frame, or in the Poisson box's ``[0, 1]^3`` frame with ``box_frame``."""
        pad = cells * self.cell
        lo, hi = self.clip[0] - pad, self.clip[1] + pad
        if box_frame:
            lo, hi = (lo - self.lower) / self.size, (hi - self.lower) / self.size
        return (torch.as_tensor(lo, dtype=like.dtype, device=like.device),
                torch.as_tensor(hi, dtype=like.dtype, device=like.device))

    def _clipped(self, verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """The faces [F', 3] whose centroid lies within one Poisson cell of the ``clip`` box (discrete)."""
        c = verts.detach()[faces.long()].mean(dim=1)
        lo, hi = self._clip_bounds(1.0, c)
        return faces[((c >= lo) & (c <= hi)).all(dim=1)]

    def thickness(self, mesh: ProxyResult, camera) -> tuple[MeshRender, torch.Tensor]:
        """How thick the proxy is where each pixel's ray enters it: ``(render, cells)``, ``render`` as
        :meth:`render` gives it and ``cells`` [H, W] (dtype of the vertices) the distance along the ray
        from the entry hit to the next surface, in Poisson grid cells (:attr:`cell`); ``inf`` on misses
        and where the ray leaves the mesh without a second hit. Discrete (no gradient); two ray casts."""
        with torch.no_grad():
            v = mesh.verts.detach()
            first = self.raycaster.raycast(v, mesh.faces, camera)
            o, d = camera.pixel_rays(v.device, v.dtype)
            length = d.norm(dim=-1)
            t0 = first.depth + _EXIT_STEP_CELLS * self.cell / length  # depth is the ray parameter (d_z = 1)
            second = self.raycaster.raycast(v, mesh.faces, None, rays=(o + d * t0[..., None], d))
            along = (second.depth * length + _EXIT_STEP_CELLS * self.cell) / self.cell
            cells = torch.where(first.mask & second.mask, along, torch.full_like(along, float("inf")))
        return first, cells

    def render(self, mesh: ProxyResult, camera) -> MeshRender:
        """Ray cast the proxy mesh from ``camera`` (BVH refitted or rebuilt as needed)."""
        return self.raycaster.raycast(mesh.verts, mesh.faces, camera)

    def closest(self, mesh: ProxyResult, points: torch.Tensor):
        """``(face_id, distance, closest)`` of ``points`` [P, 3] on the proxy mesh (discrete)."""
        return self.raycaster.closest_faces(mesh.verts.detach(), mesh.faces, points.detach())
