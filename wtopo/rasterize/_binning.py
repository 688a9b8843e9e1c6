# SPDX-License-Identifier: Apache-2.0
"""Binning of surfels to screen tiles (discrete, outside the tape), with the per-device pair capacity
that sizes the sort buffers of the fit's deferred-count path (kernels in ``kernels/rasterize_binning.py``)."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from .. import _bridge
from .._profile import section
from ..camera import Camera
from ..kernels import rasterize_binning as _kb
from ._config import RasterConfig


@dataclass
class _Bins:
    tile_start: wp.array
    tile_end: wp.array
    ids: wp.array
    radii: torch.Tensor
    means2d: torch.Tensor
    cutoff: wp.array
    prect: wp.array
    overflow: torch.Tensor | None = None
    count: torch.Tensor | None = None  # with ``pairs``: the view's pair count (int64 scalar on the device)
    exact: int | None = None  # without deferring: the pair count read (the buffers' size)


_CAPACITY_HEADROOM = 1.25  # deferred path: sort buffers hold this times the largest recent pair count ...
_CAPACITY_MIN = 4096  # ... and at least this many pairs
_CAPACITY_SHRINK = 4.0  # shrink once a count falls below 1 / this of the capacity (after fewer surfels)
_PENDING_MAX = 8  # device counts in flight at most (pinned host copies)


class _PairCapacity:
    """Number of (tile, surfel) pairs the deferred-count binning sizes its sort for, kept per device.

    Every deferred call posts its pair count into pinned host memory with a non-blocking copy and an
    event; later calls read the counts whose events have completed, so no call waits for the device.
    """

    def __init__(self):
        self.value = 0
        self.pending: deque = deque()

    def observe(self, total: int, limit: int) -> None:
        """Fit the capacity to a measured pair count (grow above it, shrink when far below)."""
        if total > self.value or total * _CAPACITY_SHRINK < self.value:
            self.value = min(limit, max(_CAPACITY_MIN, math.ceil(total * _CAPACITY_HEADROOM)))

    def post(self, total: torch.Tensor, limit: int) -> None:
        """Queue a device pair count (int64 scalar tensor) to be observed once the device has it."""
        if not total.is_cuda:
            self.observe(int(total), limit)  # CPU: the value is already there, reading it costs nothing
            return
        if len(self.pending) >= _PENDING_MAX:
            return
        host = torch.empty((), dtype=torch.int64, pin_memory=True)
        host.copy_(total, non_blocking=True)  # on the current stream of the count's device
        # the event follows that stream, not the current device's (a fit on cuda:1 with cuda:0 current would
        # otherwise see the event done and read the count before it lands)
        event = torch.cuda.Event()
        event.record(torch.cuda.current_stream(total.device))
        self.pending.append((event, host, limit))

    def poll(self) -> None:
        """Observe the posted counts that have arrived (never blocks)."""
        while self.pending and self.pending[0][0].query():
            _, host, limit = self.pending.popleft()
            self.observe(int(host), limit)


_capacities: dict[str, _PairCapacity] = {}


_iotas: dict[str, wp.array] = {}


_iotas_outgrown: list = []


def _iota(n: int, wdev) -> wp.array:
    """``0, 1, ..., n - 1`` (int32) on ``wdev``: a view of a kept array, grown when too short (never written).
    An outgrown array is kept too: a CUDA graph captured with it reads it where it is."""
    key = str(wdev)
    a = _iotas.get(key)
    if a is None or a.shape[0] < n:
        if a is not None:
            _iotas_outgrown.append(a)
        a = wp.array(np.arange(max(n, 1024, 2 * (0 if a is None else a.shape[0])), dtype=np.int32), dtype=wp.int32,
                     device=wdev)
        _iotas[key] = a
    return a[:n]


def _pair_capacity(wdev) -> _PairCapacity:
    return _capacities.setdefault(str(wdev), _PairCapacity())


def _bin(means, quats, scales, opacities, cam_rec, tables, camera: Camera, config: RasterConfig, wdev, *,
         defer_count: bool = False, pairs: int | None = None) -> _Bins:
    """Tile ranges and depth-sorted surfel ids per tile.

    With ``defer_count`` the sort buffers are sized from :class:`_PairCapacity` (counts of earlier
    calls) instead of this call's count, so nothing waits for the device; pairs beyond the capacity
    are dropped and ``overflow`` says so (a device flag). Without it the count is read (one host
    sync) and the result is always complete. ``pairs`` (N > 0): sized for that many pairs as the deferred
    path, the capacity left alone (its caller posts ``count``): what a CUDA graph of the op captures.
    ``camera``: only its ``width`` and ``height`` are read.
    """
    n = means.shape[0]
    ts = config.tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles = tiles_x * tiles_y
    dt = _bridge.float_dtype(means)
    rect = _bridge.empty(n, wp.vec4i, wdev)
    counts = _bridge.empty(n, wp.int32, wdev)
    radii = _bridge.empty(n, wp.int32, wdev)
    means2d = _bridge.empty(n, _bridge.vec_dtype(means, 2), wdev)
    cutoff = _bridge.empty(n, dt, wdev)
    prect = _bridge.empty(n, wp.vec4i, wdev)
    # centre depths, then the radix sort's scratch half (the depth order of the sort keys)
    zc = _bridge.empty(2 * n, dt, wdev)
    inputs = [_bridge.to_warp(means, _bridge.vec_dtype(means, 3)), _bridge.to_warp(quats, _bridge.vec_dtype(quats, 4)),
              _bridge.to_warp(scales, _bridge.vec_dtype(scales, 2)), _bridge.to_warp(opacities, dt), cam_rec, *tables,
              ts]
    capacity = _pair_capacity(wdev)
    overflow = None
    with section("rasterize_binning"):
        _bridge.launch_split(_kb.bin_surfels_kernel, n, inputs, [rect, counts, radii, means2d, cutoff, prect, zc],
                             device=wdev)
        counts_t = _bridge.as_torch(counts)
        pair_count = counts_t.sum(dtype=torch.int64)  # the offsets are summed later, in depth order
        defer = (defer_count or pairs is not None) and n > 0
        count = None
        if defer and pairs is not None:
            total = int(pairs)
            count = pair_count
            overflow = count > total
        elif defer:
            capacity.poll()
            if capacity.value == 0:  # host sync: once per device, the first count sizes the capacity
                capacity.observe(int(pair_count), config.max_intersections)
            # pairs sorted: the real ones, then padding keys after every tile (the capacity another call's larger
            # budget grew is cut to this call's: more pairs than that are an overflow, and the exact count raises)
            total = min(capacity.value, config.max_intersections)
            overflow = pair_count > total
            capacity.post(pair_count, config.max_intersections)
        else:
            total = int(pair_count) if n else 0  # host sync: the intersection count sizes the sort buffers
            if total <= config.max_intersections:
                capacity.observe(total, config.max_intersections)
    if total > config.max_intersections:
        raise ValueError(f"rasterize_surfels: {n} surfels cover {total} (tile, surfel) pairs, above "
                         f"config.max_intersections = {config.max_intersections}; raise the budget, use a larger "
                         f"tile_size, or prune/shrink large surfels")
    tile_start = _bridge.empty(n_tiles, wp.int32, wdev, zero=True)
    tile_end = _bridge.empty(n_tiles, wp.int32, wdev, zero=True)
    # deferred: one more tile value for the padding keys (tile n_tiles), sorted after every real pair
    key_bits = max(1, (n_tiles if defer else n_tiles - 1).bit_length())
    keys = _bridge.empty(max(2 * total, 1), wp.int32, wdev)
    values = _bridge.empty(max(2 * total, 1), wp.int32, wdev)
    if total:
        with section("rasterize_sort"):
            # the surfels' depth order (Warp's stable radix sort on the centre z-depths the binning wrote)
            order = _bridge.empty(2 * n, wp.int32, wdev)
            wp.copy(order, _iota(n, wdev), count=n)
            wp.utils.radix_sort_pairs(zc, order, n)
        with section("rasterize_binning"):
            if defer:
                keys[:total].fill_(n_tiles)
            # each surfel's first pair: the tile counts summed in depth order
            sorted_counts = torch.index_select(counts_t, 0, _bridge.as_torch(order)[:n])
            offsets = torch.cumsum(sorted_counts, 0, dtype=torch.int64) - sorted_counts
            if defer:  # pairs past the capacity are dropped: keep the offsets (int32) at most there
                offsets = offsets.clamp_max(total)
            offsets = offsets.to(torch.int32)
            _bridge.launch_split(_kb.emit_intersections_kernel, n,
                                 [order, rect, _bridge.to_warp(offsets), tiles_x, total], [keys, values],
                                 device=wdev)
        with section("rasterize_sort"):
            # by tile alone: the sort is stable and the pairs were written front to back
            wp.utils.radix_sort_pairs(keys, values, total, end_bit=key_bits)
        with section("rasterize_binning"):
            _bridge.launch_split(_kb.tile_ranges_kernel, total, [keys, total], [tile_start, tile_end],
                                 device=wdev)
    return _Bins(tile_start, tile_end, values, _bridge.as_torch(radii), _bridge.as_torch(means2d), cutoff, prect,
                 overflow, count, None if defer else total)
