# SPDX-License-Identifier: Apache-2.0
"""One slab of :func:`wtopo.tsdf_fusion.fuse_tsdf`: the block test's depth-range pyramid, the slab's marching
cubes (open where unobserved, or closed by space carving) and the seam that welds a slab to the previous one."""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from .. import _bridge
from .._profile import section
from ..kernels import tsdf_fusion as _k


def _pyramid(views: wp.array, depth: wp.array, sizes: list[tuple[int, int]], device):
    """Depth-range pyramid of every view: ``(levels [L] vec4i (offset, height, width, 0), dmin, dmax)``."""
    h, w = max(s[0] for s in sizes), max(s[1] for s in sizes)
    dims = [(h, w)]
    while dims[-1] != (1, 1):
        dims.append(((dims[-1][0] + 1) // 2, (dims[-1][1] + 1) // 2))
    n = len(sizes)
    offsets = np.cumsum([0] + [n * a * b for a, b in dims])
    dmin = wp.empty(int(offsets[-1]), dtype=wp.float32, device=device)
    dmax = wp.empty(int(offsets[-1]), dtype=wp.float32, device=device)
    _bridge.launch(_k.depth_range_base_kernel, dim=(n, h, w), inputs=[views, depth, h, w], outputs=[dmin, dmax],
              device=device)
    for li in range(1, len(dims)):
        (sh, sw), (dh, dw) = dims[li - 1], dims[li]
        _bridge.launch(_k.depth_range_reduce_kernel, dim=(n, dh, dw),
                  inputs=[int(offsets[li - 1]), sh, sw, int(offsets[li]), dh, dw], outputs=[dmin, dmax], device=device)
    levels = wp.array([wp.vec4i(int(o), a, b, 0) for o, (a, b) in zip(offsets[:-1], dims)], dtype=wp.vec4i,
                      device=device)
    return levels, dmin, dmax


class _Seam:
    """Vertices of the last slab's top layer, to weld the next slab's bottom layer onto."""

    def __init__(self):
        self.xy: torch.Tensor | None = None  # [S, 2] index-space x, y
        self.index: torch.Tensor | None = None  # [S] global vertex index

    def weld(self, verts: torch.Tensor, layer: int, start: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Global index of each of a slab's ``verts`` (index space, first layer ``layer``) and which are new.

        Vertices on ``layer`` equal (bit for bit: both slabs fuse the layer by the same arithmetic)
        to one of the previous slab's top layer take its index; the others are numbered from ``start``.
        """
        n = verts.shape[0]
        new = torch.ones(n, dtype=torch.bool, device=verts.device)
        index = torch.empty(n, dtype=torch.long, device=verts.device)
        if self.xy is not None and self.xy.shape[0] and n:
            on = torch.nonzero(verts[:, 2] == float(layer)).squeeze(1)
            if on.numel():
                keys = torch.cat([self.xy, verts[on, :2]])
                _, inv = torch.unique(keys, dim=0, return_inverse=True)
                owner = torch.full((int(inv.max()) + 1,), -1, dtype=torch.long, device=verts.device)
                owner[inv[: self.xy.shape[0]]] = self.index
                match = owner[inv[self.xy.shape[0]:]]
                hit = match >= 0
                index[on[hit]] = match[hit]
                new[on[hit]] = False
        index[new] = start + torch.arange(int(new.sum()), device=verts.device)  # host sync: slab vertex count
        return index, new

    def keep(self, verts: torch.Tensor, index: torch.Tensor, layer: int) -> None:
        """Remember the vertices of a slab's top ``layer`` with their global indices."""
        top = verts[:, 2] == float(layer)
        self.xy, self.index = verts[top, :2], index[top]


def _closed_field(tsdf: wp.array, observed: wp.array, k0: int, layers: int) -> torch.Tensor:
    """The slab's TSDF with every node decided: hidden unobserved nodes (behind some view's surface,
    seen free by none) are inside (-1), the other unobserved ones outside (+1), and so is the grid's
    outer node layer (``layers`` node layers in all), so the zero level is closed."""
    t = wp.to_torch(tsdf)
    o = wp.to_torch(observed)
    field = torch.where(o == int(_k.OBS_TSDF), t, torch.where(o == int(_k.OBS_HIDDEN), -1.0, 1.0))
    field[0], field[-1], field[:, 0], field[:, -1] = 1.0, 1.0, 1.0, 1.0
    if k0 == 0:
        field[:, :, 0] = 1.0
    if k0 + field.shape[2] == layers:
        field[:, :, -1] = 1.0
    return field


def _slab_mesh(tsdf: wp.array, observed: wp.array, color: wp.array | None, k0: int, layers: int | None = None):
    """Marching cubes of one slab in index space, faces with an unobserved edge end dropped; with
    ``layers`` (the grid's node layers) the closed field of :func:`_closed_field`, every face kept.

    Returns ``(verts [V, 3] index space, faces [F, 3] int64 into verts, colours [V, 3] uint8 or None,
    seen [V] bool: both ends of the vertex's grid edge observed)`` with only the vertices the kept faces use.
    """
    from ..marching_cubes import marching_cubes

    nx, ny, nz = tsdf.shape
    field = wp.to_torch(tsdf) if layers is None else _closed_field(tsdf, observed, k0, layers)
    with section("marching_cubes"):
        verts, faces = marching_cubes(field, 0.0, lower=(0.0, 0.0, float(k0)),
                                      upper=(float(nx - 1), float(ny - 1), float(k0 + nz - 1)))
    if faces.shape[0] == 0:
        return verts, faces.long(), None, torch.zeros(0, dtype=torch.bool, device=verts.device)
    # every vertex lies on one grid edge: floor and ceil of its index coordinates are the edge's ends
    # (one node when it rounded onto it, which MIN_ABS_TSDF keeps to edges with both ends observed)
    lo = torch.floor(verts).long()
    hi = torch.ceil(verts).long()
    stride = torch.tensor([ny * nz, nz, 1], device=verts.device)
    base = torch.tensor([0, 0, k0], device=verts.device)
    lo_i = ((lo - base) * stride).sum(1)
    hi_i = ((hi - base) * stride).sum(1)
    obs = wp.to_torch(observed).reshape(-1) == int(_k.OBS_TSDF)
    faces = faces.long()
    if layers is None:
        ok = obs[lo_i] & obs[hi_i]
        faces = faces[ok[faces].all(dim=1)]
    used = torch.zeros(verts.shape[0], dtype=torch.bool, device=verts.device)
    used[faces.reshape(-1)] = True
    remap = torch.cumsum(used.long(), 0) - 1
    faces = remap[faces]
    verts, lo_i, hi_i = verts[used], lo_i[used], hi_i[used]
    seen = obs[lo_i] & obs[hi_i]
    cols = None
    if color is not None:
        frac = (verts - torch.floor(verts)).sum(1, keepdim=True)  # the position along the one fractional axis
        c = wp.to_torch(color).reshape(-1, 3).float()
        c_lo, c_hi = c[lo_i], c[hi_i]
        if layers is not None:  # a closing vertex takes its observed end's colour (grey where neither is)
            grey = torch.full_like(c_lo, 128.0)
            o_lo, o_hi = obs[lo_i][:, None], obs[hi_i][:, None]
            c_lo, c_hi = (torch.where(o_lo, c_lo, torch.where(o_hi, c_hi, grey)),
                          torch.where(o_hi, c_hi, torch.where(o_lo, c_lo, grey)))
        cols = (c_lo * (1 - frac) + c_hi * frac + 0.5).clamp(0, 255).to(torch.uint8)
    return verts, faces, cols, seen
