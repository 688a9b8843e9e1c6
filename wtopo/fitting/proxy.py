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
from .curvature import curvature_offset
from .silhouette import SilhouetteOffset, vertex_normals
from .surfels import Surfels

__all__ = ["ProxyMesh", "ProxyResult", "poisson_mesh", "region_clip"]

_BOX_GROWTH = 0.1  # "initial_mesh" Poisson box: the TSDF mesh's box grown by 10 % (public code)
_SUPPORT_OPACITY = 0.1  # surfels at least this opaque support proxy faces (the opacity of a reset or a spawn)
_SUPPORT_SCALES = 2.0  # a surfel reaches this many of its (larger) scales from its centre
_SILHOUETTE_LIMIT_CELLS = 2.0  # the silhouette offset stays within this many Poisson grid cells
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

    Attributes:
        silhouette: the running silhouette offset (:mod:`.silhouette`; ``None`` when
            ``cfg.silhouette_gain`` is 0): :meth:`build` moves the vertices along their normals by its
            value. The fit updates it from each view's ray cast when the scene has masks.
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
        self.silhouette = None
        if float(cfg.silhouette_gain) > 0:
            if cfg.resolution is None:
                raise ValueError("mesh.silhouette_gain > 0 needs mesh.resolution set (its limit is two grid cells), "
                                 "got None: pass the configuration resolved by the plan")
            self.silhouette = SilhouetteOffset(gain=float(cfg.silhouette_gain),
                                               limit=_SILHOUETTE_LIMIT_CELLS * self.cell)

    def with_resolution(self, resolution: int) -> ProxyMesh:
        """This proxy on a grid of ``resolution`` nodes per side: the same box, prior and settings, and the
        silhouette offset's current value, clamped to the new grid's limit (two of its cells)."""
        out = ProxyMesh(replace(self.cfg, resolution=int(resolution)), box=self.box, prior=self.prior, clip=self.clip)
        if out.silhouette is not None and self.silhouette is not None:
            lim, v = out.silhouette.limit, self.silhouette.value
            out.silhouette.value = v.clamp(-lim, lim) if torch.is_tensor(v) else min(max(float(v), -lim), lim)
        return out

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

        Differentiable w.r.t. the surfel means, rotations, scales and opacities. With a
        :attr:`silhouette` offset the vertices are moved along their (discrete) normals by its value.
        With a ``clip`` box only the faces within a cell of it are kept (the vertices stay).
        """
        from ..oriented_points import oriented_points

        c = self.cfg
        with section("oriented_points"):
            op = oriented_points(surfels.means, surfels.quats, surfels.scales, surfels.opacities,
                                 samples=int(c.samples_per_surfel), offset=c.offset,
                                 opacity_threshold=c.opacity_threshold, center_weight=1.0,
                                 offset_weight=c.offset_weight, normal_sign=surfels.buffers["normal_sign"])
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
        verts, faces = poisson_mesh(pts, nrm, w, int(c.resolution), sigma=c.sigma, padding=c.padding,
                                    level_sigma=float(c.level_sigma or 0.0))
        if faces.shape[0] == 0:
            return None
        verts = self._from_box(verts)
        if self.clip is not None:
            faces = self._clipped(verts, faces)
            if faces.shape[0] == 0:
                return None
        if c.curvature_compensation:  # undo the smoothing's curvature shift (a discrete offset: same gradient)
            h = self.size * (1.0 + 2.0 * c.padding) / (int(c.resolution) - 1)
            verts = verts + curvature_offset(verts, faces, (c.sigma ** 2 + 1.0 / 6.0) * h * h, 0.5 * h)
        if self.silhouette is not None:
            verts = verts + self.silhouette.value * vertex_normals(verts, faces)
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

    def supported(self, mesh: ProxyResult, surfels: Surfels) -> torch.Tensor | None:
        """Which faces of ``mesh`` lie near a surfel (:meth:`near_surfels` at ``cfg.support_voxels``):
        bool [F] on the mesh's device, or ``None`` when ``cfg.support_voxels`` is 0 (every face supported)."""
        k = float(self.cfg.support_voxels)
        return self.near_surfels(mesh, surfels, k) if k > 0 else None

    def near_surfels(self, mesh: ProxyResult, surfels: Surfels, voxels: float) -> torch.Tensor:
        """Faces of ``mesh`` whose centroid is within ``voxels`` grid cells (of this proxy's Poisson
        domain) plus :data:`_SUPPORT_SCALES` times the larger scale of the nearest surfel centre among
        the surfels of opacity >= :data:`_SUPPORT_OPACITY`: bool [F] on the mesh's device. Discrete; a
        host round trip (KD-tree on the CPU).
        """
        from scipy.spatial import cKDTree

        f = mesh.faces.long()
        centroid = mesh.verts.detach()[f].mean(dim=1)
        opaque = surfels.opacities.detach().reshape(-1) >= _SUPPORT_OPACITY
        if not bool(opaque.any()):  # host sync: nothing opaque supports anything
            return torch.zeros(f.shape[0], dtype=torch.bool, device=f.device)
        means = surfels.means.detach()[opaque].cpu().numpy()
        reach = surfels.scales.detach()[opaque].amax(dim=1).cpu().numpy() * _SUPPORT_SCALES
        dist, idx = cKDTree(means).query(centroid.cpu().numpy())
        ok = dist <= voxels * self.cell + reach[idx]
        return torch.as_tensor(ok, device=f.device)

    def supported_pixels(self, mesh: ProxyResult, render: MeshRender, surfels: Surfels) -> torch.Tensor | None:
        """Pixels [H, W] bool of ``render`` (this proxy's :meth:`render` of ``mesh``) whose hit face is
        :meth:`supported`; ``None`` when every face is (``cfg.support_voxels`` 0). Misses are ``False``."""
        sup = self.supported(mesh, surfels)
        if sup is None:
            return None
        return render.mask & sup[render.face_id.clamp_min(0).long()]

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
