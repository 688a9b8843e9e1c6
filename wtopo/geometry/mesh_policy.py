# SPDX-License-Identifier: Apache-2.0
"""What the returned mesh keeps: the meshing policy of objects and scenes.

* Components are kept or dropped by how well the training views support them, never by rank: a
  component survives when enough views see it where their rendered (opaque) depth says a surface
  is (``_MIN_SUPPORT_VIEWS``) and it is not a sliver (``_MIN_AREA_FRACTION`` of the mesh's area).
  A torus beside a capsule keeps both; a floater seen from one direction goes.
* Scenes: the mesh is cropped to the region of interest and no face may lie within the layout's
  ``near`` distance of a camera centre (exact point-to-triangle distance): never a hull around the
  cameras. Nothing is closed or hole-filled: what was not observed stays open. A face stays only where
  ``_FACE_SUPPORT_VIEWS`` views' rendered depths put a surface at each of its vertices, within a tolerance of
  the fusion's voxel, or where the faces that fail form a small region (:func:`supported_faces`): a sheet the
  fusion made where no view shows one goes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from ..vertex_support import view_agreement
from .components import face_components

__all__ = ["crop_to_box", "crop_near_cameras", "keep_faces", "supported_components", "supported_faces"]

_MIN_SUPPORT_VIEWS = 3  # two views triangulate a point; a third guards against chance agreement
_MIN_AREA_FRACTION = 1e-3  # components below this share of the mesh's area are slivers no view resolves
# a view supports a component when this share of its vertices agree with its depth map: a closed
# surface shows at most about half of itself to one view, its silhouette band and a coarse fusion
# voxel disagree further (a fused sphere from 32-px views: ~19 % of all vertices agree within 2 %)
_SUPPORT_VERTEX_FRACTION = 0.05
_DEPTH_TOLERANCE = 0.02  # relative z-depth agreement between a vertex and a rendered depth map
_FACE_SUPPORT_VIEWS = 3  # a scene face needs this many views agreeing at each of its vertices (supported_faces)


def _used_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """[V] bool: the vertices some face of ``faces`` [F, 3] uses (a flag per vertex: ``np.unique``'s sort took 1 s at
    2.6M faces)."""
    used = np.zeros(n_vertices, bool)
    used[np.asarray(faces).reshape(-1)] = True
    return used


def keep_faces(mesh: trimesh.Trimesh, keep: np.ndarray) -> trimesh.Trimesh:
    """A new mesh of the faces ``keep`` [F] bool selects and the vertices they use, in their order, with the vertex or
    face colours and metadata: what ``copy()``, ``update_faces`` and ``remove_unreferenced_vertices`` give, without
    trimesh's cache (which hashes every array it checks: 0.7 of the 4.4-s policy at 2.6M faces on 2 CPU cores)."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)[keep]
    used = _used_vertices(f, len(v))
    number = np.cumsum(used, dtype=np.int64) - 1
    out = trimesh.Trimesh(v[used], number[f], process=False)
    kind = mesh.visual.kind
    if kind == "vertex":
        out.visual.vertex_colors = np.asarray(mesh.visual.vertex_colors)[used]
    elif kind == "face":
        out.visual.face_colors = np.asarray(mesh.visual.face_colors)[keep]
    out.metadata.update(mesh.metadata)
    return out


def _face_areas(mesh: trimesh.Trimesh, faces: np.ndarray | None = None) -> np.ndarray:
    """Area [F] (float64) of each face, or of the faces ``faces`` (indices) only: ``mesh.area_faces`` from the
    arrays, one coordinate at a time (1-D gathers), without trimesh's cache checks."""
    x, y, z = np.ascontiguousarray(np.asarray(mesh.vertices, np.float64).T)
    f = np.asarray(mesh.faces) if faces is None else np.asarray(mesh.faces)[faces]
    i, j, k = np.ascontiguousarray(f.T)
    ux, uy, uz = x[j] - x[i], y[j] - y[i], z[j] - z[i]
    wx, wy, wz = x[k] - x[i], y[k] - y[i], z[k] - z[i]
    cx, cy, cz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
    return 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)


def crop_to_box(mesh: trimesh.Trimesh, lower, upper) -> trimesh.Trimesh:
    """Faces whose three vertices lie inside the box ``[lower, upper]`` (internal units)."""
    v = np.asarray(mesh.vertices)
    inside = np.all((v >= np.asarray(lower)) & (v <= np.asarray(upper)), axis=1)
    return keep_faces(mesh, inside[np.asarray(mesh.faces)].all(axis=1))


def _face_distance(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Exact distance [F] from the point ``p`` [3] to each triangle ``tri`` [F, 3, 3]."""
    closest = trimesh.triangles.closest_point(tri, np.broadcast_to(p, (len(tri), 3)))
    return np.linalg.norm(closest - p, axis=1)


def crop_near_cameras(mesh: trimesh.Trimesh, centers: np.ndarray, near: float) -> tuple[trimesh.Trimesh, int]:
    """Remove every face with a point within ``near`` of a camera centre; returns the mesh and how many."""
    if len(mesh.faces) == 0:
        return mesh, 0
    v = np.asarray(mesh.vertices)
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    # only the cameras within ``near`` of the mesh's bounding box can be within ``near`` of a face (exact: a face
    # lies in the box); cameras outside a region of interest's mesh usually are not, and then nothing is computed
    # per face
    lo, hi = v.min(axis=0), v.max(axis=0)
    gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - centers, centers - hi)), axis=1)
    centers = centers[gap < near]
    if len(centers) == 0:
        return mesh, 0
    return _crop_near(mesh, centers, near)


def _crop_near(mesh: trimesh.Trimesh, centers: np.ndarray, near: float) -> tuple[trimesh.Trimesh, int]:
    """:func:`crop_near_cameras`' per-face pass over the cameras ``centers`` [C, 3] (float64): faces whose bounding
    sphere reaches within ``near`` of the nearest camera (a k-d tree over the few camera centres, queried by every
    face centre: 2.6M faces in about a second), then the exact point-to-triangle distance to each camera that
    sphere reaches."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    cen = (v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3.0
    rad = np.sqrt(np.max([np.einsum("ij,ij->i", v[f[:, k]] - cen, v[f[:, k]] - cen) for k in range(3)], axis=0))
    d, _ = cKDTree(centers).query(cen, k=1, workers=-1)
    cand = np.flatnonzero(d - rad < near)
    if len(cand) == 0:
        return mesh, 0
    drop = np.zeros(len(f), bool)
    tri = v[f[cand]]
    for c in centers:
        close = np.linalg.norm(cen[cand] - c, axis=1) - rad[cand] < near
        if close.any():
            ids = cand[close]
            drop[ids[_face_distance(tri[close], c) < near]] = True
    if not drop.any():
        return mesh, 0
    return keep_faces(mesh, ~drop), int(drop.sum())


def _device_views(verts: np.ndarray, depths, device):
    """``(verts, depths)``: the vertices as a float64 tensor and each depth map as a tensor on ``device`` (``None``:
    the CPU), for :func:`~wtopo.vertex_support.view_agreement`."""
    dev = torch.device("cpu" if device is None else device)
    return (torch.as_tensor(verts, dtype=torch.float64, device=dev),
            [torch.as_tensor(np.asarray(d), device=dev) for d in depths])


def supported_components(mesh: trimesh.Trimesh, cameras: Sequence, depths: Sequence[np.ndarray], *,
                         device: torch.device | str | None = None) -> tuple[trimesh.Trimesh, dict]:
    """Drop the components that too few views support, or that are slivers.

    Components are faces joined through shared vertices (:func:`~.components.face_components`). A view supports a
    component when at least ``_SUPPORT_VERTEX_FRACTION`` of the component's
    vertices agree with the view's rendered depth; a component needs ``_MIN_SUPPORT_VIEWS`` such
    views and ``_MIN_AREA_FRACTION`` of the mesh's area. Linear in faces and vertices times views
    (components are labelled once, not split into meshes); a component stops being tested once it
    has its ``_MIN_SUPPORT_VIEWS`` views (the views reported for a kept component are then a lower
    bound; a dropped component's are exact).

    Args:
        mesh: the mesh, internal frame.
        cameras: training cameras, internal frame.
        depths: their rendered z-depth maps [H, W] (0 where the surfels are not opaque).
        device: the fit's torch device, where the projections run (:func:`~wtopo.vertex_support.view_agreement`,
            float64 on every device, so the same decisions); ``None``: the CPU.

    Returns:
        ``(mesh, info)``: the kept components, and counts with the largest dropped components'
        area share and view support.
    """
    nf = len(mesh.faces)
    if nf == 0:
        return mesh, {"components": 0, "kept": 0, "dropped": []}
    faces = np.asarray(mesh.faces)
    n_comp, label = face_components(faces, len(mesh.vertices))
    area = np.bincount(label, weights=_face_areas(mesh), minlength=n_comp)
    share = area / max(float(area.sum()), 1e-300)
    vlabel = np.full(len(mesh.vertices), -1, np.int64)
    vlabel[faces.reshape(-1)] = np.repeat(label, 3)
    used = vlabel >= 0
    vcount = np.bincount(vlabel[used], minlength=n_comp).astype(np.float64)
    verts, depths = _device_views(np.asarray(mesh.vertices), depths, device)
    vlabel, vcount, views, active = (torch.as_tensor(a, device=verts.device)
                                     for a in (vlabel, vcount, np.zeros(n_comp, np.int64), np.flatnonzero(used)))
    for cam, dep in zip(cameras, depths):
        # a component that has its _MIN_SUPPORT_VIEWS views is kept whatever the other views say: only
        # the undecided ones' vertices are projected (a 700k-face scene mesh over 204 views: 5.5 s ->
        # a few views' worth); the decision and the dropped components' counts are unchanged
        if len(active) == 0:
            break
        agree = active[view_agreement(verts, active, cam, dep, relative=_DEPTH_TOLERANCE)]
        frac = torch.bincount(vlabel[agree], minlength=n_comp) / vcount.clip(min=1.0)
        views += frac >= _SUPPORT_VERTEX_FRACTION
        active = active[views[vlabel[active]] < _MIN_SUPPORT_VIEWS]
    views = views.cpu().numpy()
    keep = (views >= _MIN_SUPPORT_VIEWS) & (share >= _MIN_AREA_FRACTION)
    worst = np.argsort(-share)
    dropped = [{"area_share": round(float(share[c]), 6), "views": int(views[c])} for c in worst if not keep[c]]
    info = {"components": n_comp, "kept": int(keep.sum()), "dropped_count": len(dropped), "dropped": dropped[:10]}
    if not keep.any():  # nothing is supported: keep everything rather than return nothing
        info["kept_all_unsupported"] = True
        return mesh, info
    if keep.all():
        return mesh, info
    return keep_faces(mesh, keep[label]), info


def supported_faces(mesh: trimesh.Trimesh, cameras: Sequence, depths: Sequence[np.ndarray], tolerance: float, *,
                    min_views: int = _FACE_SUPPORT_VIEWS, min_region_area: float = 0.0,
                    device: torch.device | str | None = None) -> tuple[trimesh.Trimesh, dict]:
    """Keep the faces whose every vertex at least ``min_views`` views see where their rendered depth puts a surface.

    A view supports a vertex when the vertex projects into its image, in front of it, onto a pixel whose depth
    map is positive and within ``tolerance`` of the vertex's z-depth (the pixel it falls in: accepting any of the
    four pixel centres around it also accepts a sheet's edges, ``design/decisions.md``). The scene's fusion can
    make a sheet where no view shows a surface (under a chair's seat, which the cameras above never see:
    ``benchmarks/peers.md``); such a sheet's vertices disagree with every depth map, where the surfaces the views
    do show agree with the views that fused them.

    Args:
        mesh: the mesh, internal frame (not changed).
        cameras: training cameras, internal frame.
        depths: their rendered z-depth maps [H, W] (0 where the surfels are not opaque).
        tolerance: largest depth difference [internal units] that agrees (the fit: twice the fusion's voxel).
        min_views: views a vertex needs.
        min_region_area: unsupported faces go only as regions (faces joined through shared vertices) of at least
            this area [internal units^2]: a sheet goes, where a seen surface's few faces at a silhouette that
            coarse views miss stay (0: every unsupported face goes).
        device: the fit's torch device, where the projections run (:func:`~wtopo.vertex_support.view_agreement`,
            float64 on every device, so the same decisions); ``None``: the CPU.

    Returns:
        ``(mesh, info)``: the kept faces (the input itself when all stay) and ``{"faces": before, "kept": after}``.

    Raises:
        ValueError: ``tolerance`` not a positive finite number, ``min_views`` not an integer >= 1,
            ``min_region_area`` negative, or ``depths`` not one map per camera.
    """
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a finite depth > 0, got {tolerance!r}")
    if isinstance(min_views, bool) or not isinstance(min_views, (int, np.integer)) or min_views < 1:
        raise ValueError(f"min_views must be an integer >= 1, got {min_views!r}")
    if not (np.isfinite(min_region_area) and min_region_area >= 0):
        raise ValueError(f"min_region_area must be a finite area >= 0, got {min_region_area!r}")
    if len(depths) != len(cameras):
        raise ValueError(f"depths must hold one map per camera: {len(depths)} maps for {len(cameras)} cameras")
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        return mesh, {"faces": 0, "kept": 0}
    verts, depths = _device_views(np.asarray(mesh.vertices), depths, device)
    support = torch.zeros(len(verts), dtype=torch.int64, device=verts.device)
    active = torch.as_tensor(np.flatnonzero(_used_vertices(faces, len(verts))), device=verts.device)  # ascending
    for cam, dep in zip(cameras, depths):
        # a vertex with its min_views views is decided: only the others are projected (the result is unchanged)
        if len(active) == 0:
            break
        support[active[view_agreement(verts, active, cam, dep, tolerance=tolerance)]] += 1
        active = active[support[active] < min_views]
    support = support.cpu().numpy()
    keep = support[faces].min(axis=1) >= min_views
    if min_region_area > 0 and not keep.all():
        drop = np.flatnonzero(~keep)
        n, label = face_components(faces[drop], len(verts))
        area = np.bincount(label, weights=_face_areas(mesh, drop), minlength=n)
        keep[drop[area[label] < min_region_area]] = True
    info = {"faces": len(faces), "kept": int(keep.sum())}
    if keep.all():
        return mesh, info
    return keep_faces(mesh, keep), info
