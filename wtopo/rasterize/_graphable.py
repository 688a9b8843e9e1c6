# SPDX-License-Identifier: Apache-2.0
"""The rasterizer as a function of tensors alone, the camera included: what a CUDA graph of the op captures (the
fit's, ``wtopo.fitting.raster_graph``, and repeated public calls', ``wtopo.rasterize._replay``).

:func:`view_inputs` gives a view's camera as four cached tensors (pixel rays, the packed tile tables, the depth
row and the kernels' camera record without its clip planes); :func:`render_tensors` renders from them what
``_rasterize_trusted(..., defer_count=True)`` renders, with the sort sized for a given number of (tile, surfel)
pairs and no host read or host-side state: the clip planes and the record are made on the device, the pair count
comes back as a tensor for the caller to post to the capacity. :func:`pair_budget` rounds a pair count to the
size a capture sorts for; :func:`check_replay` and :func:`check_outputs` compare a capture's first replay with its
function run eagerly.
"""

from __future__ import annotations

import math
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
from ._run import _apply_op

_CHECK_RTOL, _CHECK_ATOL = 1e-5, 1e-6  # a first replay's images farther than this from the eager render's: off
_CHECK_GRAD_REL, _CHECK_GRAD_ABS = 1e-3, 1e-9  # ... and its gradients, relative to each one's largest entry


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


def pair_budget(capacity: int, limit: int) -> int:
    """The pair capacity a graph sorts for: ``capacity`` rounded up to a power of sqrt(2), at most ``limit``."""
    return min(int(limit), max(int(capacity), math.ceil(2 ** (math.ceil(2 * math.log2(max(capacity, 1))) / 2))))


def check_outputs(got: tuple, want: tuple) -> None:
    """Raise unless a replay's outputs ``got`` equal ``want``, the captured function's run eagerly."""
    for k, (a, b) in enumerate(zip(got, want)):
        if not torch.allclose(a.detach().double(), b.detach().double(), rtol=_CHECK_RTOL, atol=_CHECK_ATOL,
                              equal_nan=True):
            raise RuntimeError(f"output {k} of a replay differs from the eager render by "
                               f"{float((a.detach().double() - b.detach().double()).abs().max()):.3g}")


def check_replay(graphed, fn, args: tuple) -> None:
    """Raise unless a replay of ``graphed`` on ``args`` gives ``fn``'s outputs and the gradients of a fixed scalar
    of its images w.r.t. the inputs that require them."""
    diff = [a for a in args if a.requires_grad]
    got, want = graphed(*args), fn(*args)
    check_outputs(got, want)
    g = torch.Generator().manual_seed(0)
    weights = [torch.rand(got[k].shape, generator=g, dtype=got[k].dtype).to(got[k].device) for k in range(6)]
    grads = [torch.autograd.grad(sum((o[k] * w).sum() for k, w in enumerate(weights)), diff, allow_unused=True)
             for o in (got, want)]
    for k, (a, b) in enumerate(zip(*grads)):
        if a is None or b is None or not b.numel():  # an empty input ([N, 0, 3] SH bands of degree 0) included
            if (a is None) != (b is None):
                raise RuntimeError(f"the gradient of input {k} of a replay is missing or extra")
            continue
        # normwise: CUDA sums a gradient's terms with float atomics in a varying order, so an entry that nearly
        # cancels differs from run to run by a small fraction of the largest one
        same_nan = bool(torch.equal(torch.isnan(a), torch.isnan(b)))
        worst, scale = float((a - b).abs().nan_to_num(0.0).max()), float(b.abs().nan_to_num(0.0).max())
        if not (same_nan and worst <= _CHECK_GRAD_REL * scale + _CHECK_GRAD_ABS):
            raise RuntimeError(f"the gradient of input {k} of a replay differs from the eager render's by {worst:.3g} "
                               f"(largest entry {scale:.3g})")
