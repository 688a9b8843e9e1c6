# SPDX-License-Identifier: Apache-2.0
"""The fit's rasterizer as a function of tensors alone, the camera included: what a CUDA graph of the op captures
(``wtopo.fitting.raster_graph``).

:func:`view_inputs` gives a view's camera as four cached tensors (pixel rays, the packed tile tables, the depth
row and the kernels' camera record without its clip planes); :func:`render_tensors` renders from them what
``_rasterize_trusted(..., defer_count=True)`` renders, with the sort sized for a given number of (tile, surfel)
pairs and no host read or host-side state: the clip planes and the record are made on the device, the pair count
comes back as a tensor for the caller to post to the capacity.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .. import _bridge
from ..camera import Camera
from ._binning import _bin
from ._camera import (
    _camera_tables,
    _clip_from_row,
    _depth_row4,
    _packed_tables,
    _record_base,
    _record_from_base,
    _table_views,
)
from ._config import RasterConfig


class Size(NamedTuple):
    """A view's image size, all the binning and the launches read of its camera."""

    width: int
    height: int


def view_inputs(camera: Camera, device: torch.device, dtype: torch.dtype,
                config: RasterConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(rays [H, W, 3], packed tables float64 [T], depth row [4], record bytes uint8 [B])`` of ``camera`` on
    ``device`` for :func:`render_tensors` (cached on the camera; nothing is copied per call)."""
    rays, _ = _camera_tables(camera, device, dtype, config.tile_size)
    return (rays, _packed_tables(camera, device, dtype, config.tile_size), _depth_row4(camera, device, dtype),
            _record_base(camera, device, dtype, config.filter_sigma))


def render_tensors(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                   sh: torch.Tensor, shift: torch.Tensor, rays: torch.Tensor, tables: torch.Tensor, row4: torch.Tensor,
                   record: torch.Tensor, *, size: Size, sh_degree: int, background: torch.Tensor,
                   config: RasterConfig, pairs: int) -> tuple:
    """Render N > 0 surfels from a view given as :func:`view_inputs`' tensors.

    Args:
        means: centres [N, 3] (float32 or float64; the op dtype).
        quats: rotations [N, 4].
        scales: tangent scales [N, 2].
        opacities: [N].
        sh: SH coefficients [N, K, 3].
        shift: zeros ``[N, 2]`` that require grad: the screen-space gradient carrier (``RenderOutput.means2d``'s
            role; its value is never read).
        rays: the view's pixel rays [H, W, 3] (:func:`view_inputs`, as the three below).
        tables: its packed tile tables.
        row4: its depth row [4].
        record: its camera record's bytes.
        size: the view's image size.
        sh_degree: SH degree rendered.
        background: [3] on the surfels' device.
        config: the rasterizer's settings (validated).
        pairs: the sort's (tile, surfel) pair capacity (> 0).

    Returns:
        ``(rgb, alpha, depth, median, normal, distortion, visibility, radii, means2d, clip, overflow, count)``:
        the images (differentiable w.r.t. the surfels and ``shift``), the per-surfel outputs, the projected
        centres, the clip planes float64 [2], whether pairs were dropped (bool scalar) and the pair count (int64
        scalar), all on the device; the same values as ``_rasterize_trusted`` with ``defer_count`` at that
        capacity.
    """
    from . import _apply_op

    device, dtype = means.device, means.dtype
    wdev = _bridge.warp_device(device)
    with _bridge.registered_capture(device):  # Warp's sorts take their scratch inside a graph being captured
        clip = _clip_from_row(means, row4, config)
        cam_rec = _record_from_base(record, clip, dtype)
        views = _table_views(tables, size.width, size.height, config.tile_size)
        with _bridge.torch_stream(wdev, device):
            bins = _bin(means, quats, scales, opacities, cam_rec, views, size, config, wdev, pairs=pairs)
        outs = _apply_op(bins, rays, cam_rec, background.detach(), means, quats, scales, opacities, sh, shift,
                         sh_degree, size, config, wdev)
    return (*outs, bins.radii, bins.means2d, clip, bins.overflow, bins.count)
