# SPDX-License-Identifier: Apache-2.0
"""The final mesh of a fit: rendered depth fused (or the Poisson proxy), the meshing policy applied, and a
watertight Poisson re-mesh when an object's mesh is not closed (:func:`final_mesh`, :func:`poisson_remesh`)."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import numpy as np
import torch
import trimesh

from .. import _bridge
from .._profile import section
from ..geometry.mesh_policy import crop_near_cameras, crop_to_box, supported_components, supported_faces
from ..geometry.outline import offset_along_normals, outline_offset
from ..geometry.winding import is_closed
from ..raycast import MeshRaycaster
from . import densify as dens
from .config import FitConfig, NormalFlip
from .proxy import PADDING, ProxyMesh, poisson_mesh
from .scene_kind import SceneLayout
from .stages import TRUNCATION_VOXELS, Record, Renderer, is_scene, render_depths, roi_bounds
from .surfels import Surfels
from .tsdf import TSDFEmptyError, auto_bounds, cleanup_mesh, fuse_depths, repair_mesh

__all__ = ["final_mesh", "poisson_remesh"]

_PROXY_FINAL_RESOLUTION = 128  # Poisson nodes per side of the proxy mesh returned when the final TSDF is empty
_REMESH_SAMPLES = 200_000  # surface samples for the watertight Poisson re-mesh of the final mesh
_REMESH_BOX = 1.1  # the re-mesh grid spans the mesh's longest side plus 10 %: the closed surface stays inside
_SNAP_CELLS = 1.5  # re-mesh vertices within this many grid cells of the mesh move onto it (farther: hole fills)
# a scene's face stays where three views' depths agree at each vertex within this many fusion voxels, or where the
# faces that fail form a region smaller than this many voxels squared (supported_faces; design/decisions.md)
_FACE_SUPPORT_VOXELS = 2.0
_FACE_REGION_VOXELS2 = 100.0
_OUTLINE_MAX_PIXELS = 1.0  # the outline offset moves the mesh at most this many pixel footprints


def final_mesh(surfels: Surfels, cameras: Sequence, cfg: FitConfig, *, render: Renderer, proxy: ProxyMesh,
               guided: bool, tsdf_info: dict, record: Record, layout: SceneLayout | None = None,
               masks: Sequence | None = None, thin: bool = False) -> trimesh.Trimesh:
    """The returned mesh in the internal frame: TSDF of rendered depth, or the Poisson proxy when that is empty.

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
        masks: the training views' masks, one [H, W] per camera (bool or float in [0, 1]; a [N, H, W] tensor
            works), or ``None``: with ``final.outline`` an object's mesh then moves along its normals until its
            silhouettes cover them (:func:`_outline`).
        thin: the co-evolution found the object too thin for its mesh terms (:mod:`.thin_parts`): its outline is
            mostly thin parts, so the mesh may only move inward (:func:`_outline`). A fit without the co-evolution
            measures no thin parts and passes ``False``.

    Raises:
        TSDFEmptyError: the TSDF fusion and the proxy mesh are both empty.
    """
    fc = cfg.final
    mesh = None
    scene = is_scene(layout)
    depths, colors = render_depths(render, surfels, cameras)
    if scene:
        bounds = roi_bounds(layout, fc.resolution, TRUNCATION_VOXELS)
    else:
        bounds = auto_bounds(surfels.means, surfels.opacities, resolution=fc.resolution,
                             truncation_voxels=TRUNCATION_VOXELS)
    tsdf_info["final_bounds"] = bounds.to_dict()
    try:
        mesh = fuse_depths(cameras, depths, colors, bounds, device=surfels.means.device)
    except TSDFEmptyError as e:
        warnings.warn(f"final TSDF empty, returning the proxy mesh: {e}", RuntimeWarning, stacklevel=3)
        record("final_tsdf_empty", why=str(e))
    if mesh is None:
        if NormalFlip(cfg.mesh.normal_flip) != NormalFlip.RANDOM and not guided:
            # no mesh guidance ran: orient the normals by the cameras that saw each surfel (mesh mode
            # keeps the scaffold's signs)
            dens.align_normal_signs(surfels, NormalFlip(cfg.mesh.normal_flip))
        final = ProxyMesh(dataclasses.replace(cfg.mesh, resolution=_PROXY_FINAL_RESOLUTION), box=proxy.box,
                          prior=proxy.prior, clip=proxy.clip)
        with torch.no_grad():
            pm = final.build(surfels)
        if pm is None:
            raise TSDFEmptyError("no final mesh: the TSDF fusion and the proxy mesh are both empty")
        mesh = trimesh.Trimesh(pm.verts.detach().cpu().numpy(), pm.faces.cpu().numpy(), process=False)
    info: dict = {}
    dev = surfels.means.device  # where the support rules project the mesh's vertices
    # the fused and the proxy mesh come from marching cubes, which shares each edge's vertex: no merge by position
    with section("mesh_policy"):
        if scene:
            mesh = crop_to_box(mesh, layout.roi_lower, layout.roi_upper)
            mesh, info["near_camera_faces_removed"] = crop_near_cameras(mesh, layout.camera_centers, layout.near)
            mesh = cleanup_mesh(mesh, largest_component=False, repair=False, weld=False)
            with section("supported_components"):
                mesh, info["components"] = supported_components(mesh, cameras, depths, device=dev)
            with section("supported_faces"):  # a sheet the fusion made where no view shows one (never all)
                seen = depths
                if getattr(render, "unmasked", None) is not None:  # a chunked merge's views fuse their cores only
                    seen, _ = render_depths(render.unmasked, surfels, cameras)
                kept, info["faces"] = supported_faces(mesh, cameras, seen, _FACE_SUPPORT_VOXELS * bounds.voxel,
                                                      min_region_area=_FACE_REGION_VOXELS2 * bounds.voxel ** 2,
                                                      device=dev)
                mesh = kept if len(kept.faces) else mesh
        else:
            mesh = cleanup_mesh(mesh, largest_component=False, repair=False, weld=False)
            with section("supported_components"):
                mesh, info["components"] = supported_components(mesh, cameras, depths, device=dev)
            with section("repair"):  # after the support rule: repairing works component by component
                mesh = repair_mesh(mesh)
            closed = mesh.metadata.get("closed")  # repair_mesh's own test of the edges
            if fc.watertight and not (is_closed(mesh.faces) if closed is None else closed):
                mesh = poisson_remesh(mesh, cfg, record=record, device=surfels.means.device)
                # the re-mesh's closed surface can wrap the repaired mesh's inner sheets into pockets of
                # their own (a ten-view cup at 768^3: 137-343 components, no view sees most of them): the
                # same support rule as the fused mesh's; dropping closed components keeps the mesh closed
                with section("supported_components"):
                    mesh, info["remesh_components"] = supported_components(mesh, cameras, depths, device=dev)
    record("mesh_policy", policy="open_roi" if scene else "watertight", **info)
    if len(mesh.faces) == 0:
        raise TSDFEmptyError("the final mesh is empty after the meshing policy (nothing in the region of interest "
                             "that the views support)")
    if fc.outline and masks is not None and not scene:
        with section("outline"):
            mesh = _outline(mesh, cameras, masks, record=record, device=dev, thin=thin)
    return mesh


def _outline(mesh: trimesh.Trimesh, cameras: Sequence, masks: Sequence, *, record: Record,
             device: torch.device, thin: bool = False) -> trimesh.Trimesh:
    """``mesh`` moved along its normals by :func:`~wtopo.geometry.outline.outline_offset`'s distance, at most
    :data:`_OUTLINE_MAX_PIXELS` times the views' median footprint; a ``thin`` object only inward: a silhouette wider
    than the masks is too wide wherever it is, but one short of them on thin parts is parts missing or rounded
    there, not an offset. The move is measured again and undone when it did not bring the silhouettes closer to the
    masks (a part wound inward moves the wrong way) or when the moved mesh cannot be measured. Not moved when the
    outline lies on edges (too few views with smooth limbs: ``outline_offset`` measures none). Records
    ``"outline_offset"``: the median offset in pixels, the 10th-90th percentiles over the views, the views used, the
    median share of the outline on smooth limbs and the distance moved in the internal frame (0 when not moved),
    with ``skipped`` when the thin rule or the edges held it or ``undone`` (the median offset after the move) when it
    was undone."""
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        record("outline_offset", skipped="non-finite vertices", distance=0.0)
        return mesh
    caster = MeshRaycaster()  # the measure after the move refits its BVH
    off = outline_offset(mesh.vertices, mesh.faces, cameras, masks, device=device, raycaster=caster)
    if len(off.views) == 0:
        info = {"pixels": 0.0, "views": 0, "distance": 0.0}
        if len(off.shares):
            info.update(smooth_share=round(float(np.median(off.shares)), 4),
                        skipped="the outline lies on edges: a rounded edge draws it in, not a surface inside")
        record("outline_offset", **info)
        return mesh
    px = off.median_pixels
    moved = off.capped(_OUTLINE_MAX_PIXELS)
    info = {"pixels": round(px, 4), "spread": [round(float(q), 4) for q in np.percentile(off.pixels, [10, 90])],
            "views": int(len(off.views)), "smooth_share": round(float(np.median(off.shares)), 4)}
    if thin and moved > 0:
        record("outline_offset", **info, distance=0.0,
               skipped="thin parts: a silhouette short of the masks there is parts missing")
        return mesh
    if moved == 0.0:
        record("outline_offset", **info, distance=0.0)
        return mesh
    out = offset_along_normals(mesh, moved)
    again = outline_offset(out.vertices, out.faces, cameras, masks, device=device, raycaster=caster)
    after = again.median_pixels
    if len(again.views) == 0 or abs(after) >= abs(px):  # not closer, or no longer measurable: not verified
        record("outline_offset", **info, distance=0.0, undone=round(after, 4))
        return mesh
    record("outline_offset", **info, distance=moved)
    return out


def poisson_remesh(mesh: trimesh.Trimesh, cfg: FitConfig, *, record: Record,
                   device: torch.device | str = "cpu") -> trimesh.Trimesh:
    """A closed mesh through ``mesh``: Poisson of its area samples (the zero level set is closed).

    The Poisson solve and its marching cubes run on ``device`` (the fit's: at ``final.resolution``, up to
    768^3 on CUDA, the whole re-mesh took 32.6 s on 2 CPU threads against 10.2 s with an H100); a device
    other than the CPU that runs out of memory falls back to the CPU
    with a warning. The mesh keeps marching cubes' own vertex sharing (no merge by position: see
    :func:`~.tsdf.cleanup_mesh`), so it is closed at any grid; its vertices near ``mesh`` are then moved
    onto it (:func:`_snap`). Returns ``mesh`` itself when the re-mesh
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
                                sigma=1.0, padding=PADDING)
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
    verts = _snap(verts * side + lower, mesh, _SNAP_CELLS * side / int(cfg.final.resolution))
    out = trimesh.Trimesh(verts, faces, process=False)
    out = cleanup_mesh(out, largest_component=False, weld=False)
    record("poisson_remesh", watertight=is_closed(out.faces), device=str(device))
    return out if len(out.faces) else mesh


def _snap(verts: np.ndarray, mesh: trimesh.Trimesh, reach: float) -> np.ndarray:
    """``verts`` [V, 3] with each vertex within ``reach`` of ``mesh`` moved to its closest point there: the
    Poisson surface is a smoothed copy of ``mesh`` (Chamfer 0.229 -> 0.205 % on the bunny at the balanced
    preset), its own only where it closes a hole. The connectivity, hence the closedness, is the re-mesh's."""
    from ..raycast import closest_faces

    if len(verts) == 0:
        return verts
    _, dist, closest = closest_faces(torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64),
                                     torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64),
                                     torch.as_tensor(verts, dtype=torch.float64), max_distance=reach)
    near = (dist < reach).numpy()
    out = verts.copy()
    out[near] = closest.numpy()[near]
    return out


def _out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says a device allocation failed (torch's and Warp's wordings)."""
    msg = str(e).lower()
    return isinstance(e, torch.OutOfMemoryError) or "out of memory" in msg or "failed to allocate" in msg
