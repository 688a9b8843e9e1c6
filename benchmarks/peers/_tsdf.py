# SPDX-License-Identifier: Apache-2.0
"""2DGS's bounded mesh extraction (``utils/mesh_utils.py``): Open3D TSDF fusion of rendered depth, then
the largest connected clusters. Used for the gsplat peer, which has no meshing of its own."""

from __future__ import annotations

import numpy as np

__all__ = ["tsdf_mesh"]


def tsdf_mesh(frames, *, voxel_size: float = 0.004, sdf_trunc: float = 0.016, depth_trunc: float = 3.0,
              num_cluster: int = 1):
    """Fuse ``frames`` = iterable of ``(rgb [H, W, 3] in [0, 1], depth [H, W] z, K [3, 3], w2c [4, 4])``.

    Depth 0 is empty (the caller zeroes pixels of rendered opacity < 0.5, as 2DGS does). Returns a
    ``trimesh.Trimesh`` with the ``num_cluster`` largest triangle clusters (at least 50 triangles each).
    """
    import open3d as o3d
    import trimesh

    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=voxel_size, sdf_trunc=sdf_trunc, color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    for rgb, depth, K, w2c in frames:
        h, w = depth.shape
        intr = o3d.camera.PinholeCameraIntrinsic(width=w, height=h, cx=float(K[0, 2] - 0.5), cy=float(K[1, 2] - 0.5),
                                                 fx=float(K[0, 0]), fy=float(K[1, 1]))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(np.clip(rgb, 0, 1) * 255, dtype=np.uint8)),
            o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32)),
            depth_trunc=depth_trunc, convert_rgb_to_intensity=False, depth_scale=1.0)
        vol.integrate(rgbd, intrinsic=intr, extrinsic=np.asarray(w2c, dtype=np.float64))
    mesh = vol.extract_triangle_mesh()
    clusters, n_tri, _ = mesh.cluster_connected_triangles()
    clusters, n_tri = np.asarray(clusters), np.asarray(n_tri)
    if len(n_tri):
        keep = max(np.sort(n_tri)[-min(num_cluster, len(n_tri))], 50)
        mesh.remove_triangles_by_mask(n_tri[clusters] < keep)
        mesh.remove_unreferenced_vertices()
        mesh.remove_degenerate_triangles()
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=False)
