# SPDX-License-Identifier: Apache-2.0
"""Open3D TSDF fusion regression: 0.20.0's ScalableTSDFVolume returns empty meshes, 0.19.0 works.

Open3D is the tests' reference TSDF fusion (``tests/reference/tsdf_open3d.py``; the fit fuses with its own Warp
kernel). The ``test`` extra pins open3d(-cpu)==0.19.0 for that reason; this test fails loudly if an install picks
up a broken build, instead of the reference silently producing no mesh.
"""

import numpy as np
import pytest

o3d = pytest.importorskip("open3d")

# A plane 1 m in front of a 64x64 pinhole camera, fused with 2 cm voxels: the mesh must cover the
# camera's footprint on the plane (about 1.2 m x 1.2 m at fov 62 deg).
_W = _H = 64
_F = 50.0
_DEPTH = 1.0
_VOXEL = 0.02


def _fuse_plane(volume_cls, **kwargs):
    volume = volume_cls(voxel_length=_VOXEL, sdf_trunc=4 * _VOXEL,
                        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, **kwargs)
    intr = o3d.camera.PinholeCameraIntrinsic(_W, _H, _F, _F, _W / 2, _H / 2)
    color = o3d.geometry.Image(np.full((_H, _W, 3), 128, np.uint8))
    depth = o3d.geometry.Image(np.full((_H, _W), _DEPTH, np.float32))
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        color, depth, depth_scale=1.0, depth_trunc=10.0, convert_rgb_to_intensity=False)
    volume.integrate(rgbd, intr, np.eye(4))
    return volume.extract_triangle_mesh()


def test_open3d_version_is_pinned():
    """Run with the Open3D version whose TSDF fusion is known to work."""
    assert o3d.__version__.startswith("0.19."), o3d.__version__


def test_scalable_tsdf_fuses_a_plane():
    """Fuse a fronto-parallel plane and get a non-empty mesh at the right depth and extent."""
    mesh = _fuse_plane(o3d.pipelines.integration.ScalableTSDFVolume)
    verts = np.asarray(mesh.vertices)
    assert len(mesh.triangles) > 100, len(mesh.triangles)
    # surface within one voxel of the plane
    np.testing.assert_allclose(np.median(verts[:, 2]), _DEPTH, atol=_VOXEL)
    extent = verts[:, 0].max() - verts[:, 0].min()
    footprint = _W / _F * _DEPTH
    assert extent > 0.8 * footprint, (extent, footprint)
