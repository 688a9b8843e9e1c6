# SPDX-License-Identifier: Apache-2.0
"""TSDF fusion of z-depth (and colour) maps into a mesh with Warp, on CPU or CUDA.

:func:`fuse_tsdf` integrates every view into a dense grid of TSDF nodes, one z-slab at a time, and
extracts each slab's zero level with :func:`wtopo.marching_cubes.marching_cubes`
(:mod:`wtopo.kernels.tsdf_fusion` has the per-node rule). Per slab:

* a block test (blocks of ``BLOCK`` nodes per side, whole grid, once) marks the blocks some view's
  truncation band may reach; nodes of the other blocks are written unobserved without projecting
  (``cull=False`` projects every node: the mesh is the same);
* one launch fuses every view into every node of the slab (one thread per node, all views in its
  loop: nothing is allocated per view);
* marching cubes of the slab in node-index coordinates; a face is kept when both ends of every
  vertex's grid edge were observed, so unobserved nodes make no face and the surface is open where
  nothing was seen; vertex colours are interpolated along the same edges;
* the slab's vertices on the layer it shares with the previous slab are welded to that slab's.

Memory: the views (4 bytes of depth and 3 of colour per pixel, and the block test's depth-range
pyramid of 8 bytes per texel, about 11 per pixel over its levels: some 18 bytes per pixel in all,
0.4 GB for 48 views of 800 x 600), the block flags (1 byte per ``BLOCK^3`` nodes), and per slab at most
``slab_nodes`` nodes of 8 bytes (TSDF, observed flag, colour) plus marching cubes' 2 bytes per
node and its output. With the default ``SLAB_NODES`` (2^25) a slab takes about 350 MB whatever the
grid size: a 768^3 grid is fused in 14 slabs. Only the mesh grows with the grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from ..camera import Camera
from ..kernels import tsdf_fusion as _k
from ._fusion import BLOCK, SLAB_NODES, _Fusion, _slab_limit
from ._slab import _Seam, _slab_mesh

__all__ = ["TSDFMesh", "TSDFVolume", "fuse_tsdf", "tsdf_volume", "BLOCK", "SLAB_NODES"]


@dataclass
class TSDFMesh:
    """What :func:`fuse_tsdf` returns.

    Attributes:
        verts: vertex positions [V, 3], float32, world units (the cameras' frame), on the fusion's device.
        faces: [F, 3] int32 indices into ``verts``, wound so normals point towards the cameras (out
            of the surface: increasing TSDF).
        colors: vertex colours [V, 3] uint8, or ``None`` when no colours were fused.
        shape: nodes of the grid along x, y, z.
    """

    verts: torch.Tensor
    faces: torch.Tensor
    colors: torch.Tensor | None
    shape: tuple[int, int, int]


@dataclass
class TSDFVolume:
    """What :func:`tsdf_volume` returns: the fused grid, node ``(i, j, k)`` at ``lower + (i, j, k) * voxel``.

    Attributes:
        tsdf: mean truncated signed distance in truncation units [X, Y, Z], float32, in ``[-1, 1]``
            (positive in front of the surface); 1 where unobserved.
        observed: [X, Y, Z] bool, whether any view contributed to the node.
        free: [X, Y, Z] bool, unobserved nodes some view's ray crossed on its way to no surface (the
            node projects onto a pixel without depth); ``False`` where observed.
        hidden: [X, Y, Z] bool, unobserved nodes not ``free`` that lie deeper than the truncation
            behind some view's depth.
        colors: mean colour [X, Y, Z, 3] uint8 (0 where unobserved), or ``None``.
        lower: position of node ``(0, 0, 0)`` [3], float64, world units.
        voxel: node spacing, world units.
    """

    tsdf: torch.Tensor
    observed: torch.Tensor
    free: torch.Tensor
    hidden: torch.Tensor
    colors: torch.Tensor | None
    lower: np.ndarray
    voxel: float


def fuse_tsdf(cameras: Sequence[Camera], depths: Sequence, colors: Sequence | None = None, *, lower, upper,
              voxel: float, truncation: float, far: Sequence[float] | None = None,
              device: torch.device | str | None = None, cull: bool = True,
              slab_nodes: int | None = None, close: bool = False) -> TSDFMesh:
    """Fuse z-depth maps (and colours) into a TSDF on a dense grid and extract its zero level.

    Each node of the grid is projected into every view through that camera's own lens model (pose,
    ``K`` with skew and principal point, OpenCV distortion; a distorted lens sees nothing beyond
    the field its image covers, as :func:`wtopo.geometry.depth_warp.pinhole_warp` measures it) and
    reads the depth of the pixel it falls in. A view contributes ``min(1, sdf / truncation)``
    with weight 1 when its depth is valid (``0 < d < far``) and ``sdf = (d - z) * |p| / z > -truncation``
    (``z``: the node's camera depth, ``|p|``: its distance to the camera): Open3D's
    ``ScalableTSDFVolume`` rule. The surface is the zero level of the mean, kept only where both
    nodes of each vertex's grid edge were observed by some view: open where nothing was seen.

    With ``close``, nothing is left undecided and the surface is closed (space carving): an
    unobserved node that lies deeper than the truncation behind some view's depth and that no view's
    ray crosses on its way to no surface (a pixel without depth) is inside; every other unobserved
    node (seen empty, or seen by no view) and the grid's outer node layer are outside. Where no
    view saw the surface, the mesh then closes along the boundary of the space the views saw empty,
    the tightest closure the views allow (a cup's unseen floor, the underside of an object on a rig
    above it).

    Args:
        cameras: one :class:`wtopo.Camera` per view (world frame of the grid).
        depths: per view a z-depth map [H, W] (the camera's image size), float, world units; 0 (or
            negative) marks no measurement. NumPy arrays or tensors, on any device; must be finite.
        colors: ``None``, or per view an RGB image [H, W, 3] in [0, 1] (rounded to 8 bits).
        lower: grid origin, the position of node ``(0, 0, 0)`` [3], world units.
        upper: the grid reaches at least this corner [3] (nodes up to the first at or past it).
        voxel: node spacing, world units.
        truncation: truncation distance, world units.
        far: per view a depth cut-off (depths at or beyond it are no data); ``None``: none.
        device: where to fuse (``"cpu"``, ``"cuda:N"``); ``None``: the first tensor depth's device,
            else the CPU.
        cull: skip the nodes of blocks no view's truncation band reaches (the mesh is the same
            either way; ``False`` projects every node into every view).
        slab_nodes: most nodes fused at once (memory bound); ``None``: :data:`SLAB_NODES`.
        close: close the surface by carving (above). Every node is projected (``cull`` is ignored:
            a culled block would not know whether a view saw it free).

    Returns:
        A :class:`TSDFMesh` on ``device``; zero faces (and vertices) when nothing was fused or no
        surface crosses the observed nodes. Discrete: nothing is differentiable.

    Raises:
        TypeError: a camera is not a :class:`wtopo.Camera`, a map or number has a wrong type.
        ValueError: counts or map sizes do not match the cameras, a depth or colour value is NaN or
            infinite (checked before any launch), ``upper <= lower``, ``voxel`` or ``truncation``
            not > 0, a ``far`` not > 0, ``slab_nodes`` below two node layers.

    Limitations:
        Dense in each slab: the time grows with the grid's volume where the band reaches (the block
        test skips the rest) and with the view count per node. A node reads the nearest pixel, no
        interpolation (as Open3D). Colours are averaged with the depths' weights, 8 bits per channel.

    References:
        B. Curless, M. Levoy, "A volumetric method for building complex models from range images",
        SIGGRAPH 1996. Q.-Y. Zhou, J. Park, V. Koltun, "Open3D: A modern library for 3D data
        processing", 2018 (``ScalableTSDFVolume``).
    """
    fu = _Fusion(cameras, depths, colors, lower, upper, voxel, truncation, far, device, cull and not close)
    limit = _slab_limit(slab_nodes, fu.shape)
    dev = fu.device
    empty = TSDFMesh(torch.zeros(0, 3, device=dev), torch.zeros(0, 3, dtype=torch.int32, device=dev),
                     torch.zeros(0, 3, dtype=torch.uint8, device=dev) if fu.has_color else None, fu.shape)
    if fu.n_views == 0:
        return empty
    out_v, out_f, out_c, out_s = [], [], [], []
    seam = _Seam()
    count = 0
    with fu.scope():
        for k0, tsdf, observed, color in fu.slabs(limit):
            verts, faces, cols, seen = _slab_mesh(tsdf, observed, color, k0, fu.shape[2] if close else None)
            if faces.shape[0] == 0:
                seam = _Seam()
                continue
            index, new = seam.weld(verts, k0, count)
            count += int(new.sum())  # host sync: vertex count (one per slab)
            out_v.append(verts[new])
            out_f.append(index[faces])
            if cols is not None:
                out_c.append(cols[new])
            out_s.append(seen[new])
            seam.keep(verts, index, k0 + tsdf.shape[2] - 1)
    if not out_f:
        return empty
    verts = torch.cat(out_v) * fu.voxel + torch.as_tensor(fu.lower, dtype=torch.float32, device=dev)
    faces, cols = torch.cat(out_f), (torch.cat(out_c) if fu.has_color else None)
    if close:
        verts, faces, cols = _drop_unseen_components(verts, faces, cols, torch.cat(out_s))
    return TSDFMesh(verts, faces.to(torch.int32), cols, fu.shape)


def _drop_unseen_components(verts, faces, cols, seen):
    """Keep the connected components of a closed mesh that hold a vertex of observed surface: a
    component made only of closing faces encloses space a view or two saw behind a surface and none
    saw empty (a grid corner in one view's shadow), not an object. Host round trip (SciPy)."""
    from ..geometry.components import face_components

    f = faces.cpu().numpy()
    _, label = face_components(f, verts.shape[0])
    keep = np.zeros(label.max() + 1, bool)
    keep[label[seen.cpu().numpy()[f].any(axis=1)]] = True
    keep_f = keep[label]
    if keep_f.all():
        return verts, faces, cols
    used = np.zeros(verts.shape[0], bool)
    used[f[keep_f]] = True
    f = (np.cumsum(used) - 1)[f[keep_f]]
    kv = torch.as_tensor(used, device=verts.device)
    return verts[kv], torch.as_tensor(f, device=faces.device), None if cols is None else cols[kv]


def tsdf_volume(cameras: Sequence[Camera], depths: Sequence, colors: Sequence | None = None, *, lower, upper,
                voxel: float, truncation: float, far: Sequence[float] | None = None,
                device: torch.device | str | None = None, cull: bool = True,
                slab_nodes: int | None = None) -> TSDFVolume:
    """The fused TSDF grid of :func:`fuse_tsdf` itself (same rule, same arguments), whole.

    Allocates the whole grid (8 bytes per node with colours, 5 without): for small grids, tests
    and inspection; :func:`fuse_tsdf` keeps only one slab at a time. Arguments and errors are those
    of :func:`fuse_tsdf`.

    Returns:
        A :class:`TSDFVolume` on ``device``. With ``cull``, nodes of blocks outside every view's
        truncation band read unobserved (1) even where a view saw them as free space (also 1).
    """
    fu = _Fusion(cameras, depths, colors, lower, upper, voxel, truncation, far, device, cull)
    limit = _slab_limit(slab_nodes, fu.shape)
    dev = fu.device
    tsdf = torch.ones(fu.shape, dtype=torch.float32, device=dev)
    observed = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    free = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    hidden = torch.zeros(fu.shape, dtype=torch.bool, device=dev)
    colors_out = torch.zeros(fu.shape + (3,), dtype=torch.uint8, device=dev) if fu.has_color else None
    if fu.n_views:
        with fu.scope():
            for k0, t, o, c in fu.slabs(limit):
                k1 = k0 + t.shape[2]
                tsdf[:, :, k0:k1] = wp.to_torch(t)
                state = wp.to_torch(o)
                observed[:, :, k0:k1] = state == int(_k.OBS_TSDF)
                free[:, :, k0:k1] = state == int(_k.OBS_FREE)
                hidden[:, :, k0:k1] = state == int(_k.OBS_HIDDEN)
                if c is not None:
                    colors_out[:, :, k0:k1] = wp.to_torch(c)
    return TSDFVolume(tsdf, observed, free, hidden, colors_out, fu.lower.copy(), fu.voxel)
