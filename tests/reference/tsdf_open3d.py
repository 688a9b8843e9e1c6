# SPDX-License-Identifier: Apache-2.0
"""Open3D 0.19's ``ScalableTSDFVolume`` under the fit's fusion rule: an independent implementation of
:func:`wtopo.fitting.tsdf.fuse_depths` (Open3D's own sparse voxel blocks, integration and marching cubes) for
the tests to compare the Warp fusion with. Needs Open3D (the ``test`` extra installs it).

Same rule: truncation ``bounds.truncation``, each view's depth cut off at the bounds' farthest corner, weight 1
per view. Open3D takes only a pinhole intrinsic, so a distorted or skewed view is first resampled onto the
ideal pinhole camera of the same pose that covers its field (:func:`wtopo.geometry.depth_warp.pinhole_warp`).
"""

from __future__ import annotations

import numpy as np

from wtopo.fitting.tsdf import _far_depth as far_depth
from wtopo.geometry.depth_warp import pinhole_warp

__all__ = ["fuse_open3d", "fuse_depths_open3d"]


def fuse_open3d(views: list, bounds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Open3D ``ScalableTSDFVolume`` of ``views`` ``(camera, depth [H, W] float32, colour [H, W, 3] in [0, 1])``
    with ``bounds`` (:class:`wtopo.fitting.tsdf.FusionBounds`): vertices, faces, uint8 colours."""
    import open3d as o3d

    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=bounds.voxel, sdf_trunc=bounds.truncation,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    for cam, dep, col in views:
        # Open3D takes only a pinhole intrinsic: a distorted or skewed view is first resampled onto
        # the ideal pinhole camera of the same pose that covers its field (depth_warp).
        warp = pinhole_warp(cam)
        dep = np.ascontiguousarray(warp.resample_depth(dep))
        # Open3D puts pixel centres at integer coordinates; wtopo at +0.5 (camera.py).
        intr = o3d.camera.PinholeCameraIntrinsic(warp.width, warp.height, warp.K[0, 0], warp.K[1, 1],
                                                 warp.K[0, 2] - 0.5, warp.K[1, 2] - 0.5)
        rgb = np.ascontiguousarray(warp.resample((col * 255).astype(np.uint8)))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(dep), depth_scale=1.0,
            depth_trunc=far_depth(cam, bounds), convert_rgb_to_intensity=False)
        vol.integrate(rgbd, intr, cam.world_to_camera)
    mesh = vol.extract_triangle_mesh()
    c = np.asarray(mesh.vertex_colors)
    return (np.asarray(mesh.vertices), np.asarray(mesh.triangles),
            (np.clip(c, 0, 1) * 255).astype(np.uint8) if c.size else np.zeros((0, 3), np.uint8))


def fuse_depths_open3d(cameras, depths, colors, bounds):
    """:func:`wtopo.fitting.tsdf.fuse_depths`'s contract on :func:`fuse_open3d`: views without depth skipped,
    a ``trimesh.Trimesh`` (merged vertices, vertex colours) cropped to ``bounds`` grown by a voxel."""
    import trimesh

    views = []
    for cam, dep, col in zip(cameras, depths, colors):
        dep = np.ascontiguousarray(np.nan_to_num(np.asarray(dep, np.float32), nan=0.0, posinf=0.0, neginf=0.0))
        if (dep > 0).any():
            views.append((cam, dep, np.clip(np.asarray(col, np.float32), 0, 1)))
    v, f, c = fuse_open3d(views, bounds)
    tm = trimesh.Trimesh(v, f, vertex_colors=c if c.size else None, process=True)
    inside = np.all((tm.vertices >= bounds.lower - bounds.voxel) & (tm.vertices <= bounds.upper + bounds.voxel), axis=1)
    tm.update_faces(inside[tm.faces].all(axis=1))
    tm.remove_unreferenced_vertices()
    return tm
