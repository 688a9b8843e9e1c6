# SPDX-License-Identifier: Apache-2.0
"""The TSDF re-initialisation stage: the warm-up surfels replaced by one surfel per face of a TSDF fusion of
their rendered depth (:func:`tsdf_reinit`)."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence

import numpy as np
import torch
import trimesh

from ..geometry.mesh_policy import supported_components
from .config import FitConfig, PoissonBox
from .proxy import ProxyMesh, region_clip
from .scene_kind import SceneLayout
from .stages import ROI_EXTENT, TRUNCATION_VOXELS, Record, Renderer, is_scene, render_depths, roi_bounds
from .surfels import Surfels
from .tsdf import TSDFEmptyError, auto_bounds, cleanup_mesh, fuse_depths, hybrid_keep, mesh_to_surfels, repair_mesh

__all__ = ["Reinit", "tsdf_reinit"]

_REINIT_MAX_VIEWS = 64  # the re-initialisation fuses at most this many (evenly spaced) views: enough coverage
_HYBRID_DISTANCE = 0.02  # hybrid rule: surfels farther than this (extent fraction) from the TSDF mesh keep their
# warm-up parameters
_REINIT_OPACITY = 0.8  # TSDF re-initialised surfels start nearly opaque: they sit on the fused surface
_PRIOR_SAMPLES = 20000  # surface samples of the re-initialisation mesh kept as the proxy's surface prior


@dataclasses.dataclass
class Reinit:
    """What :func:`tsdf_reinit` produced.

    Attributes:
        surfels: the re-initialised surfels, or ``None`` when the fusion was empty (keep the old ones).
        info: bounds and counts, stored in the report's ``"tsdf"``.
        proxy: the proxy mesh bounded by or with the prior of the fused mesh, or ``None`` to keep the current one.
    """

    surfels: Surfels | None
    info: dict
    proxy: ProxyMesh | None = None


def tsdf_reinit(surfels: Surfels, cameras: Sequence, cfg: FitConfig, *, render: Renderer,
                background_rule: bool, record: Record, layout: SceneLayout | None = None) -> Reinit:
    """Fuse the rendered depth of ``surfels`` and put one surfel on each face of the fused mesh.

    With ``background_rule``, the old surfels farther than ``_HYBRID_DISTANCE`` from that mesh
    are kept (background the object's TSDF does not cover) and every component of the mesh is kept.
    Without it, the mesh keeps the components the views support
    (:func:`~wtopo.geometry.mesh_policy.supported_components`, never by rank: a torus beside a capsule
    keeps both; counts in ``info["components"]``). A scene (``layout.kind``) fuses only its region of
    interest. An empty fusion keeps the warm-up surfels (event ``"tsdf_empty"``).
    """
    tc, device = cfg.tsdf, surfels.means.device
    cams = cameras[:: max(1, math.ceil(len(cameras) / _REINIT_MAX_VIEWS))]
    depths, colors = render_depths(render, surfels, cams)
    s = surfels
    if is_scene(layout):
        bounds = roi_bounds(layout, tc.resolution, TRUNCATION_VOXELS)
    else:
        bounds = auto_bounds(s.means, s.opacities, resolution=tc.resolution, truncation_voxels=TRUNCATION_VOXELS)
    info = {"reinit_bounds": bounds.to_dict()}
    try:
        mesh = fuse_depths(cams, depths, colors, bounds, device=device)
    except TSDFEmptyError as e:
        warnings.warn(f"TSDF re-initialisation skipped, keeping the warm-up surfels: {e}", RuntimeWarning,
                      stacklevel=3)
        record("tsdf_empty", why=str(e))
        return Reinit(None, info)
    if background_rule:
        mesh = cleanup_mesh(mesh, largest_component=False)
    else:
        # the components the views support, never the largest alone: a torus beside a capsule keeps both (the
        # final mesh's rule); repaired after the support rule, which drops the specks first (see repair_mesh)
        mesh = cleanup_mesh(mesh, largest_component=False, repair=False)
        mesh, info["components"] = supported_components(mesh, cams, depths, device=device)
        mesh = repair_mesh(mesh)
    new = mesh_to_surfels(mesh, max_faces=tc.max_faces, device=device, sh_degree=s.sh_degree, opacity=_REINIT_OPACITY)
    kept = 0
    if background_rule:
        from ..raycast import closest_faces

        v = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=device)
        f = torch.as_tensor(mesh.faces, dtype=torch.int32, device=device)
        _, dist, _ = closest_faces(v, f, s.means.detach())
        p, b = hybrid_keep(s, dist, _HYBRID_DISTANCE * ROI_EXTENT)
        kept = int(p["means"].shape[0])
        new.append(p, b)
    proxy = None
    if cfg.mesh.poisson_box == PoissonBox.INITIAL_MESH or cfg.mesh.surface_prior > 0:
        pts, fi = trimesh.sample.sample_surface(mesh, _PRIOR_SAMPLES, seed=cfg.runtime.seed)
        prior = (torch.as_tensor(pts, dtype=torch.float32, device=device),
                 torch.as_tensor(mesh.face_normals[fi], dtype=torch.float32, device=device))
        box = mesh.bounds if cfg.mesh.poisson_box == PoissonBox.INITIAL_MESH else None
        proxy = ProxyMesh(cfg.mesh, box=box, prior=prior, clip=region_clip(cfg.mesh, layout))
        info["poisson_box"] = None if box is None else np.asarray(box).tolist()
    info.update({"reinit_faces": int(len(mesh.faces)), "reinit_surfels": len(new) - kept, "hybrid_kept": kept})
    record("tsdf_reinit", **info)
    return Reinit(new, info, proxy)
