# SPDX-License-Identifier: Apache-2.0
"""Trilinear scatter of point values onto a grid, and its adjoint, trilinear sampling.

Grid convention: an ``R^3`` grid has node ``(i, j, k)`` at position ``(i, j, k) / R`` of the unit
cube. Points must lie in ``[0, 1)^3``. A point in the last cell of an axis (coordinate in
``[(R-1)/R, 1)``) has upper neighbours with index ``R``, which do not exist: their share is
dropped (the grid is extended by zeros, never wrapped periodically), in both the scatter and the
sample, so the two stay exact adjoints. Coordinates outside ``[0, 1)`` raise :class:`ValueError`.

CPU parallelism and determinism: Warp's CPU ``atomic_add`` is not atomic across concurrent
launches, so the scatter splits the *grid* into slabs of the first index, one per CPU thread,
sized to hold about equally many points (a histogram of the first coordinate); every thread
reads all points and writes only its slab. Each node is therefore written by one
thread, in point order: CPU results are bitwise deterministic for any thread count. On CUDA one
launch with hardware atomics is used (summation order, hence the last bits, may vary run to run).
"""

from __future__ import annotations

import math

import torch
import warp as wp

from . import _bridge
from ._validate import require_finite, require_int_range, require_same_device, require_tensor
from .kernels.scatter_trilinear import sample_trilinear_kernel, scatter_trilinear_kernel, trilinear_point_grad_kernel

__all__ = ["scatter_trilinear", "sample_trilinear"]

# Below this many points a scatter runs as one launch: fanning out costs more than it saves.
_MIN_SPLIT_POINTS = 16384
_compiled: set = set()


def _balanced_slabs(points: wp.array, resolution: int, threads: int) -> list[int]:
    """Slab bounds over the first node index holding about equally many points each (one pass, CPU)."""
    x = wp.to_torch(points)[:, 0]
    cell = (x * resolution).floor().to(torch.int64).clamp_(0, resolution - 1)
    cdf = torch.bincount(cell, minlength=resolution).cumsum(0)
    targets = torch.arange(1, threads, dtype=cdf.dtype) * (int(cdf[-1]) // threads)
    inner = (torch.searchsorted(cdf, targets) + 1).tolist()
    bounds = [0]
    for b in inner:
        if bounds[-1] < b < resolution:
            bounds.append(int(b))
    return [*bounds, resolution]


def scatter_launch(points: wp.array, values: wp.array, resolution: int, grid: wp.array) -> None:
    """Accumulate the trilinear scatter of ``values`` at ``points`` into ``grid`` (``R^3`` C-vectors), not taped."""
    n = points.shape[0]
    if n == 0:
        return
    device = points.device
    threads = _bridge.cpu_threads() if device.is_cpu and n >= _MIN_SPLIT_POINTS else 1
    threads = min(threads, resolution)
    bounds = _balanced_slabs(points, resolution, threads) if threads > 1 else [0, resolution]
    threads = len(bounds) - 1

    def _run(t: int) -> None:
        _bridge.launch(scatter_trilinear_kernel, dim=n, inputs=[points, values, resolution, bounds[t], bounds[t + 1]],
                  outputs=[grid], device=device, record_tape=False)

    key = (str(device), points.dtype, values.dtype)
    if threads == 1 or key not in _compiled:
        # The first launch compiles the overload: run it alone so threads never race on a build.
        for t in range(threads):
            _run(t)
        _compiled.add(key)
        return
    futures = [_bridge._get_pool(threads).submit(_run, t) for t in range(threads)]  # noqa: SLF001 - shared pool
    for f in futures:
        f.result()


def sample_launch(grid: wp.array, points: wp.array, resolution: int, out: wp.array) -> None:
    """Accumulate trilinear samples of ``grid`` (``R^3`` C-vectors) at ``points`` into ``out`` (``N``), not taped."""
    _bridge.launch_split(sample_trilinear_kernel, points.shape[0], [grid, points, resolution], [out],
                         device=points.device)


def point_grad_launch(grid: wp.array, per_point: wp.array, points: wp.array, resolution: int,
                      adj_points: wp.array) -> None:
    """Accumulate ``sum_nodes dw/dp <grid[node], per_point[n]>`` into ``adj_points``, not taped."""
    _bridge.launch_split(trilinear_point_grad_kernel, points.shape[0], [grid, per_point, points, resolution],
                         [adj_points], device=points.device)


# Channels per launch: node values are Warp vectors of length 1..4 (wider values are chunked).
_MAX_CHANNELS = 4
_CHANNEL_TYPES = {(dt, c): wp.types.vector(length=c, dtype=wdt)
                  for dt, wdt in ((torch.float32, wp.float32), (torch.float64, wp.float64)) for c in range(1, 5)}


def _types(dtype: torch.dtype, channels: int):
    """Warp point type and node-vector type for a torch float dtype and 1..4 channels."""
    return _bridge.vec_dtype(torch.empty(0, 3, dtype=dtype)), _CHANNEL_TYPES[(dtype, channels)]


def _scatter_op(dtype: torch.dtype, resolution: int, channels: int) -> _bridge.WarpOp:
    v3, vc = _types(dtype, channels)

    def run(points, values):
        grid = wp.zeros(resolution ** 3, dtype=vc, device=points.device)
        tape = _bridge.active_tape()  # None: nothing differentiates this call (the final re-mesh), no gradient grid
        if tape is not None:
            # The bridge copies the upstream gradient into grid.grad before anything reads it (one output),
            # so it is left unzeroed: that spares touching R^3*C fresh pages in every forward.
            grid.grad = wp.empty_like(grid)
        scatter_launch(points, values, resolution, grid)
        if tape is not None:
            def backward():
                if values.requires_grad:
                    sample_launch(grid.grad, points, resolution, values.grad)
                if points.requires_grad:
                    point_grad_launch(grid.grad, values, points, resolution, points.grad)

            tape.record_func(backward, [a for a in (points, values, grid) if a.requires_grad])
        return (grid,)

    return _bridge.WarpOp("scatter_trilinear", run, (v3, vc), (True, True), (True,))


def _sample_op(dtype: torch.dtype, resolution: int, channels: int) -> _bridge.WarpOp:
    v3, vc = _types(dtype, channels)

    def run(grid, points):
        tape = _bridge.active_tape()  # None: nothing differentiates this call, no gradient array
        out = wp.zeros(points.shape[0], dtype=vc, device=points.device, requires_grad=tape is not None)
        sample_launch(grid, points, resolution, out)
        if tape is not None:
            def backward():
                if grid.requires_grad:
                    scatter_launch(points, out.grad, resolution, grid.grad)
                if points.requires_grad:
                    point_grad_launch(grid, out.grad, points, resolution, points.grad)

            tape.record_func(backward, [a for a in (grid, points, out) if a.requires_grad])
        return (out,)

    return _bridge.WarpOp("sample_trilinear", run, (vc, v3), (True, True), (True,))


def scatter_unchecked(points: torch.Tensor, values: torch.Tensor, resolution: int) -> torch.Tensor:
    """:func:`scatter_trilinear` without validation (callers guarantee shapes, dtypes and range)."""
    n, channels = values.shape
    if n == 0:
        # No launch on empty inputs; keep the (empty) inputs in the graph so backward gives
        # zero-size gradients of the right shape.
        zero = points.sum() * 0 + values.sum() * 0
        return zero + torch.zeros(resolution, resolution, resolution, channels, dtype=values.dtype,
                                  device=values.device)
    if channels > _MAX_CHANNELS:
        return torch.cat([scatter_unchecked(points, values[:, c:c + _MAX_CHANNELS], resolution)
                          for c in range(0, channels, _MAX_CHANNELS)], dim=-1)
    (grid,) = _bridge.apply(_scatter_op(values.dtype, resolution, channels), points, values)
    return grid.view(resolution, resolution, resolution, channels)


def sample_unchecked(grid: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """:func:`sample_trilinear` without validation (callers guarantee shapes, dtypes and range)."""
    resolution, channels = grid.shape[0], grid.shape[3]
    if points.shape[0] == 0:
        return points.sum() * 0 + grid.sum() * 0 + torch.zeros(0, channels, dtype=grid.dtype, device=grid.device)
    if channels > _MAX_CHANNELS:
        return torch.cat([sample_unchecked(grid[..., c:c + _MAX_CHANNELS], points)
                          for c in range(0, channels, _MAX_CHANNELS)], dim=-1)
    (out,) = _bridge.apply(_sample_op(grid.dtype, resolution, channels),
                           grid.reshape(resolution ** 3, channels), points)
    return out.view(-1, channels)


def _extremes(t: torch.Tensor) -> tuple[float, float]:
    """``(min, max)`` of ``t`` in one pass (NaN propagates into both).  Host sync."""
    if t.numel() == 0:
        return 0.0, 0.0
    mn, mx = torch.aminmax(t.detach())
    return float(mn), float(mx)


def check_finite(name: str, t: torch.Tensor) -> None:
    """Raise :class:`ValueError` naming the first NaN/inf of ``t`` (one-pass fast path).  Host sync."""
    mn, mx = _extremes(t)
    if not (math.isfinite(mn) and math.isfinite(mx)):
        require_finite(name, t.detach())


def check_unit_points(name: str, points: torch.Tensor, lo: float, hi: float, *, closed: bool) -> None:
    """Raise :class:`ValueError` naming the first coordinate of ``points`` outside ``[lo, hi)`` (or ``[lo, hi]``)."""
    p = points.detach()
    mn, mx = _extremes(p)
    if mn >= lo and (mx <= hi if closed else mx < hi):  # False for NaN
        return
    require_finite(name, p)
    bad = (p < lo) | ((p > hi) if closed else (p >= hi))
    i, j = (int(v) for v in torch.nonzero(bad)[0].tolist())
    rng = f"[{lo}, {hi}]" if closed else f"[{lo}, {hi})"
    raise ValueError(f"{name} must lie in {rng} on every axis (no periodic wrap), got {p[i, j].item()!r} "
                     f"at index [{i}, {j}]")


def scatter_trilinear(points: torch.Tensor, values: torch.Tensor, resolution: int) -> torch.Tensor:
    """Splat per-point values onto a regular grid with trilinear weights.

    ``grid[i, j, k] = sum_n w_n(i, j, k) * values[n]`` where ``w_n`` is the trilinear weight of
    point ``n`` at node ``(i, j, k)``, located at ``(i, j, k) / R``. Shares that would fall on the
    non-existent nodes of index ``R`` are dropped (zero extension, no periodic wrap).

    Args:
        points: positions in the unit cube, shape ``[N, 3]``, float32 or float64, every coordinate
            in ``[0, 1)``; anything else (including NaN) raises :class:`ValueError`.
        values: per-point values, shape ``[N, C]`` with any ``C >= 1`` (launched 4 channels at a
            time), dtype of ``points``.
        resolution: ``R >= 2``, nodes per axis.

    Returns:
        ``grid``, shape ``[R, R, R, C]``, dtype of ``values``. Differentiable w.r.t. ``points``
        (trilinear weights are C0: the gradient jumps across cell faces) and ``values``. CPU results
        are bitwise deterministic.
    """
    require_tensor("points", points, shape=(None, 3))
    n = points.shape[0]
    require_tensor("values", values, shape=(n, None), dtypes=(points.dtype,))
    if values.shape[1] < 1:
        raise ValueError(f"values must have at least one channel, got shape {list(values.shape)}")
    require_same_device(points=points, values=values)
    require_int_range("resolution", resolution, 2)
    check_unit_points("points", points, 0.0, 1.0, closed=False)
    check_finite("values", values)
    return scatter_unchecked(points, values, resolution)


def sample_trilinear(grid: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Interpolate a grid trilinearly at points: the adjoint of :func:`scatter_trilinear`.

    Args:
        grid: node values, shape ``[R, R, R, C]`` (node ``(i, j, k)`` at ``(i, j, k) / R``),
            float32 or float64. Nodes of index ``R`` read as 0.
        points: positions, shape ``[N, 3]``, dtype of ``grid``, every coordinate in ``[0, 1)``.

    Returns:
        ``[N, C]`` samples. Differentiable w.r.t. ``grid`` and ``points``.
    """
    require_tensor("grid", grid, ndim=4)
    r = grid.shape[0]
    if tuple(grid.shape[:3]) != (r, r, r) or r < 2 or grid.shape[3] < 1:
        raise ValueError(f"grid must have shape [R, R, R, C] with R >= 2 and C >= 1, got {list(grid.shape)}")
    require_tensor("points", points, shape=(None, 3), dtypes=(grid.dtype,))
    require_same_device(grid=grid, points=points)
    check_unit_points("points", points, 0.0, 1.0, closed=False)
    return sample_unchecked(grid, points)
