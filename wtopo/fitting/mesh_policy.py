# SPDX-License-Identifier: Apache-2.0
"""What the returned mesh keeps: the meshing policy of objects and scenes.

* Components are kept or dropped by how well the training views support them, never by rank: a
  component survives when enough views see it where their rendered (opaque) depth says a surface
  is (``_MIN_SUPPORT_VIEWS``) and it is not a sliver (``_MIN_AREA_FRACTION`` of the mesh's area).
  A torus beside a capsule keeps both; a floater seen from one direction goes.
* Scenes: the mesh is cropped to the region of interest and no face may lie within the layout's
  ``near`` distance of a camera centre (exact point-to-triangle distance): never a hull around the
  cameras. Nothing is closed or hole-filled: what was not observed stays open.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh

__all__ = ["crop_to_box", "crop_near_cameras", "camera_clearance", "supported_components"]

_MIN_SUPPORT_VIEWS = 3  # two views triangulate a point; a third guards against chance agreement
_MIN_AREA_FRACTION = 1e-3  # components below this share of the mesh's area are slivers no view resolves
# a view supports a component when this share of its vertices agree with its depth map: a closed
# surface shows at most about half of itself to one view, its silhouette band and a coarse fusion
# voxel disagree further (a fused sphere from 32-px views: ~19 % of all vertices agree within 2 %)
_SUPPORT_VERTEX_FRACTION = 0.05
_SUPPORT_SAMPLES = 2000  # vertices tested per component (evenly strided)
_DEPTH_TOLERANCE = 0.02  # relative z-depth agreement between a vertex and a rendered depth map


def crop_to_box(mesh: trimesh.Trimesh, lower, upper) -> trimesh.Trimesh:
    """Faces whose three vertices lie inside the box ``[lower, upper]`` (internal units)."""
    v = np.asarray(mesh.vertices)
    inside = np.all((v >= np.asarray(lower)) & (v <= np.asarray(upper)), axis=1)
    out = mesh.copy()
    out.update_faces(inside[out.faces].all(axis=1))
    out.remove_unreferenced_vertices()
    return out


def _face_distance(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Exact distance [F] from the point ``p`` [3] to each triangle ``tri`` [F, 3, 3]."""
    closest = trimesh.triangles.closest_point(tri, np.broadcast_to(p, (len(tri), 3)))
    return np.linalg.norm(closest - p, axis=1)


def camera_clearance(mesh: trimesh.Trimesh, centers: np.ndarray) -> np.ndarray:
    """Distance [N] from each camera centre [N, 3] to the nearest point of ``mesh`` (inf when empty)."""
    out = np.full(len(centers), np.inf)
    if len(mesh.faces) == 0:
        return out
    tri = np.asarray(mesh.triangles)
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(axis=1)
    for i, c in enumerate(np.asarray(centers, np.float64)):
        lower = np.linalg.norm(cen - c, axis=1) - rad  # a lower bound of each face's distance
        order = np.argsort(lower)
        best = np.inf
        for start in range(0, len(order), 4096):  # exact distances in blocks, nearest bounds first
            blk = order[start:start + 4096]
            if lower[blk[0]] >= best:
                break
            best = min(best, float(_face_distance(tri[blk], c).min()))
        out[i] = best
    return out


def crop_near_cameras(mesh: trimesh.Trimesh, centers: np.ndarray, near: float) -> tuple[trimesh.Trimesh, int]:
    """Remove every face with a point within ``near`` of a camera centre; returns the mesh and how many."""
    if len(mesh.faces) == 0:
        return mesh, 0
    tri = np.asarray(mesh.triangles)
    cen = tri.mean(axis=1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(axis=1)
    drop = np.zeros(len(tri), bool)
    for c in np.asarray(centers, np.float64):
        cand = np.nonzero(np.linalg.norm(cen - c, axis=1) - rad < near)[0]
        if len(cand):
            drop[cand[_face_distance(tri[cand], c) < near]] = True
    if not drop.any():
        return mesh, 0
    out = mesh.copy()
    out.update_faces(~drop)
    out.remove_unreferenced_vertices()
    return out, int(drop.sum())


def _view_support(points: np.ndarray, cameras: Sequence, depths: Sequence[np.ndarray]) -> np.ndarray:
    """Per view, the share of ``points`` [P, 3] visible where its depth map [H, W] (z, 0 = none) agrees."""
    out = np.zeros(len(cameras))
    for k, (cam, dep) in enumerate(zip(cameras, depths)):
        uv, z = cam.project(points)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        if not ok.any():
            continue
        d = np.asarray(dep)[v[ok], u[ok]]
        agree = (d > 0) & (np.abs(d - z[ok]) <= _DEPTH_TOLERANCE * z[ok])
        out[k] = agree.sum() / len(points)
    return out


def supported_components(mesh: trimesh.Trimesh, cameras: Sequence, depths: Sequence[np.ndarray]
                         ) -> tuple[trimesh.Trimesh, dict]:
    """Drop the components that too few views support, or that are slivers.

    Args:
        mesh: the mesh, internal frame.
        cameras: training cameras, internal frame.
        depths: their rendered z-depth maps [H, W] (0 where the surfels are not opaque).

    Returns:
        ``(mesh, info)``: the kept components merged, and counts with each dropped component's
        area share and view support.
    """
    if len(mesh.faces) == 0:
        return mesh, {"components": 0, "dropped": []}
    parts = mesh.split(only_watertight=False)
    total = float(sum(p.area for p in parts)) or 1.0
    keep, dropped = [], []
    for p in parts:
        share = float(p.area) / total
        pts = np.asarray(p.vertices)[:: max(1, len(p.vertices) // _SUPPORT_SAMPLES)]
        views = int((_view_support(pts, cameras, depths) >= _SUPPORT_VERTEX_FRACTION).sum())
        if views >= _MIN_SUPPORT_VIEWS and share >= _MIN_AREA_FRACTION:
            keep.append(p)
        else:
            dropped.append({"area_share": round(share, 6), "views": views, "faces": int(len(p.faces))})
    info = {"components": len(parts), "kept": len(keep), "dropped": dropped}
    if not keep:  # nothing is supported: keep everything rather than return nothing
        info["kept_all_unsupported"] = True
        return mesh, info
    return (keep[0] if len(keep) == 1 else trimesh.util.concatenate(keep)), info
