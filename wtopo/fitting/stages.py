# SPDX-License-Identifier: Apache-2.0
"""The discrete stages around the loop: TSDF re-initialisation and the final mesh.

:class:`Stage` names the stages (its values are stored in history records and checkpoints).
:func:`tsdf_reinit` replaces the warm-up surfels by one surfel per face of a TSDF fusion of their
rendered depth; :func:`final_mesh` fuses rendered depth (or builds the Poisson proxy) into the mesh
the fit returns, re-meshed by :func:`poisson_remesh` when it is not closed.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import torch
import trimesh

from .. import _bridge
from .._profile import section
from ..geometry.mesh_policy import crop_near_cameras, crop_to_box, supported_components
from ..scene import NORMALIZATION_MARGIN
from . import densify as dens
from .config import Closure, FinalMethod, FitConfig, NormalFlip, PoissonBox, RenderedDepth
from .proxy import ProxyMesh, poisson_mesh, region_clip
from .scene_kind import SceneKind, SceneLayout
from .silhouette import calibrate_mesh
from .surfels import Surfels
from .tsdf import (
    FusionBounds,
    TSDFEmptyError,
    auto_bounds,
    cleanup_mesh,
    fuse_depths,
    hybrid_keep,
    mesh_to_surfels,
    repair_mesh,
)

__all__ = ["Stage", "ROI_EXTENT", "Renderer", "render_depths", "tsdf_reinit", "final_mesh", "poisson_remesh"]

ROI_EXTENT = 1.0 - 2 * NORMALIZATION_MARGIN
"""Side of the region of interest in the internal frame: :meth:`wtopo.Scene.normalization` maps it
into ``[m, 1 - m]^3`` (``m = wtopo.scene.NORMALIZATION_MARGIN`` on every side of the unit cube). Distances given
relative to the scene extent are multiplied by this."""
_REINIT_MAX_VIEWS = 64  # the re-initialisation fuses at most this many (evenly spaced) views: enough coverage
_HYBRID_DISTANCE = 0.02  # hybrid rule: surfels farther than this (extent fraction) from the TSDF mesh keep their
# warm-up parameters
_REINIT_OPACITY = 0.8  # TSDF re-initialised surfels start nearly opaque: they sit on the fused surface
_PRIOR_SAMPLES = 20000  # surface samples of the re-initialisation mesh kept as the proxy's surface prior
_REMESH_SAMPLES = 200_000  # surface samples for the watertight Poisson re-mesh of the final mesh
_REMESH_BOX = 1.1  # the re-mesh grid spans the mesh's longest side plus 10 %: the closed surface stays inside

_ROI_FUSION_MARGIN = 0.05  # scenes fuse the region of interest grown by this fraction of its side (the
# surface at its border is not cut by the fusion's own boundary; the crop to the region comes after)

Record = Callable[..., None]
"""``record(event, **fields)`` appends an event tagged with the current iteration."""


class Stage(str, enum.Enum):
    """A stage of the fit; the value is what history records and checkpoints store."""

    WARMUP = "warmup"
    """Photometric fit with density control, no mesh loss."""
    TSDF = "tsdf"
    """Re-initialisation of the surfels from a TSDF fusion of their rendered depth."""
    COEVOLUTION = "coevolution"
    """Fit with the differentiable proxy mesh and mesh guidance."""
    FINAL = "final"
    """The returned mesh."""


class Renderer:
    """Renders surfels with the fit's background and rasterizer settings.

    Args:
        background: background colour, shape [3], float32, on the fit's device.
        config: :class:`wtopo.rasterize.RasterConfig` of the fit.
    """

    def __init__(self, background: torch.Tensor, config):
        from ..rasterize._config import _validate_config

        self.background = background
        self.config = _validate_config(config)  # once: the per-call path does not check it again

    def __call__(self, surfels: Surfels, camera, *, defer_count: bool = False):
        """:func:`wtopo.rasterize.rasterize_surfels` of ``surfels`` seen by ``camera`` (differentiable).

        The fit's tensors are its own and checked by its guards, so the op's argument checks (host
        synchronisations on CUDA) are skipped. ``defer_count``: size the binning from earlier
        calls without reading this call's count; the caller checks ``overflow`` of the output and
        renders again (without it) when set.
        """
        from ..rasterize import _rasterize_trusted

        s = surfels
        # on CPU reading the count costs nothing and sorting only the real pairs is faster
        defer = defer_count and s.means.is_cuda
        return _rasterize_trusted(s.means, s.quats, s.scales, s.opacities, s.sh, camera, sh_degree=s.sh_degree,
                                  background=self.background, config=self.config, defer_count=defer)


def render_depths(render: Renderer, surfels: Surfels, cameras: Sequence, which: RenderedDepth,
                  alpha_threshold: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Depth maps [H, W] (``which`` rendered depth) and colours [H, W, 3] per camera, as NumPy;
    depth is zero where the rendered opacity is below ``alpha_threshold``."""
    depths, colors = [], []
    with torch.no_grad(), section("render_depths"):
        for cam in cameras:
            out = render(surfels, cam)
            d = out.median_depth if which == RenderedDepth.MEDIAN else out.depth
            d = torch.where(out.alpha >= alpha_threshold, d, torch.zeros_like(d))
            depths.append(d.detach().cpu().numpy())
            colors.append(out.rgb.detach().clamp(0, 1).cpu().numpy())
    return depths, colors


def _is_scene(layout: SceneLayout | None) -> bool:
    return layout is not None and layout.kind is SceneKind.SCENE


def roi_bounds(layout: SceneLayout, resolution: int, truncation_voxels: float) -> FusionBounds:
    """Fusion bounds of a scene: the region of interest grown by ``_ROI_FUSION_MARGIN``, ``resolution``
    voxels along its longest side."""
    side = float(np.max(layout.roi_upper - layout.roi_lower))
    lo = layout.roi_lower - _ROI_FUSION_MARGIN * side
    hi = layout.roi_upper + _ROI_FUSION_MARGIN * side
    voxel = float(np.max(hi - lo)) / int(resolution)
    return FusionBounds(lo, hi, voxel, truncation_voxels * voxel)


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
    are kept (background the object's TSDF does not cover) and the mesh is not cut to its largest
    component. A scene (``layout.kind``) fuses only its region of interest. An empty fusion keeps
    the warm-up surfels (event ``"tsdf_empty"``).
    """
    tc, device = cfg.tsdf, surfels.means.device
    cams = cameras[:: max(1, math.ceil(len(cameras) / _REINIT_MAX_VIEWS))]
    depths, colors = render_depths(render, surfels, cams, tc.depth, tc.alpha_threshold)
    s = surfels
    if _is_scene(layout):
        bounds = roi_bounds(layout, tc.resolution, tc.truncation_voxels)
    else:
        bounds = auto_bounds(s.means, s.opacities, resolution=tc.resolution, truncation_voxels=tc.truncation_voxels)
    info = {"reinit_bounds": bounds.to_dict()}
    try:
        mesh = fuse_depths(cams, depths, colors, bounds, backend=tc.backend, device=device)
    except TSDFEmptyError as e:
        warnings.warn(f"TSDF re-initialisation skipped, keeping the warm-up surfels: {e}", RuntimeWarning,
                      stacklevel=3)
        record("tsdf_empty", why=str(e))
        return Reinit(None, info)
    mesh = cleanup_mesh(mesh, largest_component=not background_rule)
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


def final_mesh(surfels: Surfels, cameras: Sequence, cfg: FitConfig, *, render: Renderer, proxy: ProxyMesh,
               guided: bool, tsdf_info: dict, record: Record, layout: SceneLayout | None = None,
               masks=None) -> trimesh.Trimesh:
    """The returned mesh in the internal frame: TSDF of rendered depth, or the Poisson proxy.

    Args:
        surfels: the fitted surfels.
        cameras: training cameras (internal frame).
        cfg: configuration (``final``, ``tsdf``, ``mesh``).
        render: the fit's renderer.
        proxy: the co-evolution proxy (its box and prior bound the final Poisson mesh).
        guided: mesh guidance ran (the normal signs are aligned already).
        tsdf_info: updated in place with the final fusion bounds.
        record: event sink (``"final_tsdf_empty"``, ``"poisson_remesh"``, ``"mesh_policy"``).
        layout: scene kind and region of interest; a scene's mesh is its region of interest's
            surface, open, with no face within ``layout.near`` of a camera centre
            (:mod:`.mesh_policy`). Objects are closed. Both keep the components the views support.
        masks: the training views' [H, W] bool masks or ``None``; with ``final.silhouette_calibration``
            an object's mesh is moved onto them (:func:`~.silhouette.calibrate_mesh`).

    Raises:
        TSDFEmptyError: the TSDF fusion and the proxy mesh are both empty.
    """
    fc = cfg.final
    mesh = None
    scene = _is_scene(layout)
    carve = False
    weld = True  # merge vertices by position in the clean-up; not a marching-cubes mesh's (see cleanup_mesh)
    depths, colors = render_depths(render, surfels, cameras, cfg.tsdf.depth, cfg.tsdf.alpha_threshold)
    if fc.method == FinalMethod.TSDF:
        if scene:
            bounds = roi_bounds(layout, fc.resolution, cfg.tsdf.truncation_voxels)
        else:
            bounds = auto_bounds(surfels.means, surfels.opacities, resolution=fc.resolution,
                                 truncation_voxels=cfg.tsdf.truncation_voxels)
        tsdf_info["final_bounds"] = bounds.to_dict()
        carve = not scene and fc.watertight and Closure(fc.closure) == Closure.CARVE
        try:
            mesh = fuse_depths(cameras, depths, colors, bounds, backend=cfg.tsdf.backend,
                               device=surfels.means.device, close=carve)
        except TSDFEmptyError as e:
            warnings.warn(f"final TSDF empty, returning the proxy mesh: {e}", RuntimeWarning, stacklevel=3)
            record("final_tsdf_empty", why=str(e))
    if mesh is None:
        if NormalFlip(cfg.mesh.normal_flip) != NormalFlip.RANDOM and not guided:
            # no mesh guidance ran: orient the normals by the cameras that saw each surfel (mesh mode
            # keeps the scaffold's signs)
            dens.align_normal_signs(surfels, NormalFlip(cfg.mesh.normal_flip))
        final = ProxyMesh(dataclasses.replace(cfg.mesh, resolution=fc.poisson_resolution), box=proxy.box,
                          prior=proxy.prior, clip=proxy.clip)
        with torch.no_grad():
            pm = final.build(surfels)
        if pm is None:
            raise TSDFEmptyError("no final mesh: the TSDF fusion and the proxy mesh are both empty")
        mesh = trimesh.Trimesh(pm.verts.detach().cpu().numpy(), pm.faces.cpu().numpy(), process=False)
        weld = False
    info: dict = {}
    with section("mesh_policy"):
        if scene:
            mesh = crop_to_box(mesh, layout.roi_lower, layout.roi_upper)
            mesh, info["near_camera_faces_removed"] = crop_near_cameras(mesh, layout.camera_centers, layout.near)
            mesh = cleanup_mesh(mesh, largest_component=fc.largest_component, repair=False, weld=weld)
            with section("supported_components"):
                mesh, info["components"] = supported_components(mesh, cameras, depths)
        else:
            mesh = cleanup_mesh(mesh, largest_component=fc.largest_component, repair=False, weld=weld)
            with section("supported_components"):
                mesh, info["components"] = supported_components(mesh, cameras, depths)
            with section("repair"):  # after the support rule: repairing works component by component
                mesh = repair_mesh(mesh)
            info["closure"] = "carve" if carve else "poisson"
            if fc.watertight and not mesh.is_watertight:
                mesh = poisson_remesh(mesh, cfg, record=record, device=surfels.means.device)
                # the re-mesh's closed surface can wrap the repaired mesh's inner sheets into pockets of
                # their own (a ten-view cup at 768^3: 137-343 components, no view sees most of them): the
                # same support rule as the fused mesh's; dropping closed components keeps the mesh closed
                with section("supported_components"):
                    mesh, info["remesh_components"] = supported_components(mesh, cameras, depths)
            if fc.silhouette_calibration and masks is not None and len(mesh.faces):
                with section("silhouette_calibration"):
                    v, cal = calibrate_mesh(torch.as_tensor(mesh.vertices), torch.as_tensor(mesh.faces), cameras, masks)
                mesh = trimesh.Trimesh(v.numpy(), mesh.faces, process=False)
                record("silhouette_calibration", **cal)
    record("mesh_policy", policy="open_roi" if scene else "watertight", **info)
    if len(mesh.faces) == 0:
        raise TSDFEmptyError("the final mesh is empty after the meshing policy (nothing in the region of interest "
                             "that the views support)")
    return mesh


def poisson_remesh(mesh: trimesh.Trimesh, cfg: FitConfig, *, record: Record,
                   device: torch.device | str = "cpu") -> trimesh.Trimesh:
    """A closed mesh through ``mesh``: Poisson of its area samples (the zero level set is closed).

    The Poisson solve and its marching cubes run on ``device`` (the fit's: at ``final.resolution``, up to
    768^3 on CUDA, the whole re-mesh took 32.6 s on 2 CPU threads against 10.2 s with an H100,
    ``benchmarks/final_remesh.py``); a device other than the CPU that runs out of memory falls back to the CPU
    with a warning. The mesh keeps marching cubes' own vertex sharing (no merge by position: see
    :func:`~.tsdf.cleanup_mesh`), so it is closed at any grid. Returns ``mesh`` itself when the re-mesh
    comes out empty; records ``"poisson_remesh"`` (``watertight``, and the ``device`` it ran on).
    """
    pts, fi = trimesh.sample.sample_surface(mesh, _REMESH_SAMPLES, seed=cfg.runtime.seed)
    lo, hi = mesh.bounds
    side = float(np.max(hi - lo)) * _REMESH_BOX
    lower = 0.5 * (lo + hi) - 0.5 * side
    p = torch.as_tensor((pts - lower) / side, dtype=torch.float32)
    n = torch.as_tensor(mesh.face_normals[fi], dtype=torch.float32)
    device = torch.device(device)

    def solve(dev: torch.device):
        with torch.no_grad():
            v, f = poisson_mesh(p.to(dev), n.to(dev), torch.ones(p.shape[0], device=dev), int(cfg.final.resolution),
                                sigma=1.0, padding=cfg.mesh.padding)
            return v.cpu().numpy(), f.cpu().numpy()

    try:
        verts, faces = solve(device)
    except RuntimeError as e:  # torch.OutOfMemoryError is one; Warp's allocation failures are others
        if device.type == "cpu" or not _out_of_memory(e):
            raise
        warnings.warn(f"the final Poisson re-mesh at {cfg.final.resolution}^3 ran out of memory on {device}; "
                      f"re-meshing on the CPU instead ({e})", RuntimeWarning, stacklevel=2)
        if device.type == "cuda":
            torch.cuda.empty_cache()
            _bridge.recover_after_oom(device)  # the next render's sort would otherwise fail (Warp 1.19)
        device = torch.device("cpu")
        verts, faces = solve(device)
    # marching cubes shares each vertex already: no merge by position (see cleanup_mesh's weld)
    out = trimesh.Trimesh(verts * side + lower, faces, process=False)
    out = cleanup_mesh(out, largest_component=cfg.final.largest_component, weld=False)
    record("poisson_remesh", watertight=bool(out.is_watertight), device=str(device))
    return out if len(out.faces) else mesh


def _out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says a device allocation failed (torch's and Warp's wordings)."""
    msg = str(e).lower()
    return isinstance(e, torch.OutOfMemoryError) or "out of memory" in msg or "failed to allocate" in msg
