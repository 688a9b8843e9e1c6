# SPDX-License-Identifier: Apache-2.0
"""Warp kernels for :func:`wtopo.ops.scatter_trilinear` and its adjoint :func:`wtopo.ops.sample_trilinear`.

Grid node ``(i, j, k)`` of an ``R^3`` grid sits at ``(i, j, k) / R``; grids are stored flat as
``R^3`` vectors of ``C`` channels (``C`` in 1..4, a Warp ``vector(length=C)``; :mod:`wtopo.scatter`
splits wider values into chunks) with node index ``(i*R + j)*R + k``. A vector per node rather
than a loop over channels made the CPU scatter about 1.5x faster. Nodes with an index of ``R`` (the cell between
the last node and ``1.0``) do not exist: their weight is dropped (zero extension, never a periodic
wrap). All kernels are generic over float32/float64 and *accumulate* into their output, so they
serve both as forward passes (into zeroed arrays) and as explicit adjoints (into gradient buffers).
They are never differentiated by the tape: :mod:`wtopo.scatter` registers them as each other's
adjoints.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def corner_weight(d: int, f: Any):
    """Linear weight of the lower (``d = 0``) or upper (``d = 1``) node for fraction ``f``."""
    if d == 0:
        return type(f)(1.0) - f
    return f


@wp.func
def corner_slope(d: int, f: Any):
    """Derivative of :func:`corner_weight` with respect to ``f``."""
    if d == 0:
        return type(f)(-1.0)
    return type(f)(1.0)


@wp.func
def trilinear_cell(p: Any, resolution: int):
    """Lower node ``(i0, j0, k0)`` of the cell holding ``p`` and the fractions ``(fx, fy, fz)`` inside it."""
    r = type(p[0])(float(resolution))
    u = p * r
    b = wp.vector(wp.floor(u[0]), wp.floor(u[1]), wp.floor(u[2]))
    f = u - b
    return int(b[0]), int(b[1]), int(b[2]), f[0], f[1], f[2]


@wp.kernel
def scatter_trilinear_kernel(
    points: wp.array[Any],
    values: wp.array[Any],
    resolution: int,
    slab_lo: int,
    slab_hi: int,
    grid: wp.array[Any],
):
    """Add ``w * values[n]`` to the 8 nodes around point ``n`` whose first index is in ``[slab_lo, slab_hi)``.

    On CPU each concurrent launch owns a disjoint slab of first indices, so plain read-modify-write
    ``atomic_add`` is safe and every node sums its points in index order (deterministic). On CUDA
    one launch covers all slabs and ``atomic_add`` is a hardware atomic. The 8 corners are written
    out by hand: the looped form (as in the gathers below) ran about 3x slower on CPU.
    """
    n = wp.tid()
    i0, j0, k0, fx, fy, fz = trilinear_cell(points[n], resolution)
    r = resolution
    x0 = i0 >= slab_lo and i0 < slab_hi
    x1 = i0 + 1 >= slab_lo and i0 + 1 < slab_hi and i0 + 1 < r
    if not (x0 or x1):
        return
    y1 = j0 + 1 < r
    z1 = k0 + 1 < r
    one = type(fx)(1.0)
    gx = one - fx
    gy = one - fy
    gz = one - fz
    base = (i0 * r + j0) * r + k0
    rr = r * r
    v = values[n]
    if x0:
        wp.atomic_add(grid, base, (gx * gy * gz) * v)
        if z1:
            wp.atomic_add(grid, base + 1, (gx * gy * fz) * v)
        if y1:
            wp.atomic_add(grid, base + r, (gx * fy * gz) * v)
            if z1:
                wp.atomic_add(grid, base + r + 1, (gx * fy * fz) * v)
    if x1:
        wp.atomic_add(grid, base + rr, (fx * gy * gz) * v)
        if z1:
            wp.atomic_add(grid, base + rr + 1, (fx * gy * fz) * v)
        if y1:
            wp.atomic_add(grid, base + rr + r, (fx * fy * gz) * v)
            if z1:
                wp.atomic_add(grid, base + rr + r + 1, (fx * fy * fz) * v)


@wp.kernel
def sample_trilinear_kernel(
    offset: int,
    grid: wp.array[Any],
    points: wp.array[Any],
    resolution: int,
    out: wp.array[Any],
):
    """Add the trilinear interpolation of ``grid`` at point ``n`` to ``out[n]`` (one thread per point)."""
    n = offset + wp.tid()
    i0, j0, k0, fx, fy, fz = trilinear_cell(points[n], resolution)
    acc = out[n]
    for di in range(2):
        i = i0 + di
        if i < resolution:
            wx = corner_weight(di, fx)
            for dj in range(2):
                j = j0 + dj
                if j < resolution:
                    wxy = wx * corner_weight(dj, fy)
                    for dk in range(2):
                        k = k0 + dk
                        if k < resolution:
                            acc += (wxy * corner_weight(dk, fz)) * grid[(i * resolution + j) * resolution + k]
    out[n] = acc


@wp.kernel
def trilinear_point_grad_kernel(
    offset: int,
    grid: wp.array[Any],
    per_point: wp.array[Any],
    points: wp.array[Any],
    resolution: int,
    adj_points: wp.array[Any],
):
    """Add ``sum_nodes dw/dp * <grid[node], per_point[n]>`` to ``adj_points[n]``.

    This is the position gradient of both ops: for the scatter ``grid`` is the upstream gradient of
    the grid and ``per_point`` the values; for the sample ``grid`` is the sampled grid and
    ``per_point`` the upstream gradient of the samples.
    """
    n = offset + wp.tid()
    i0, j0, k0, fx, fy, fz = trilinear_cell(points[n], resolution)
    pv = per_point[n]
    gx = type(fx)(0.0)
    gy = type(fx)(0.0)
    gz = type(fx)(0.0)
    for di in range(2):
        i = i0 + di
        if i < resolution:
            wx = corner_weight(di, fx)
            sx = corner_slope(di, fx)
            for dj in range(2):
                j = j0 + dj
                if j < resolution:
                    wy = corner_weight(dj, fy)
                    sy = corner_slope(dj, fy)
                    for dk in range(2):
                        k = k0 + dk
                        if k < resolution:
                            wz = corner_weight(dk, fz)
                            sz = corner_slope(dk, fz)
                            s = wp.dot(grid[(i * resolution + j) * resolution + k], pv)
                            gx += sx * wy * wz * s
                            gy += wx * sy * wz * s
                            gz += wx * wy * sz * s
    # d(u)/d(p) = R for every axis.
    r = type(fx)(float(resolution))
    adj_points[n] = adj_points[n] + type(adj_points[n])(gx * r, gy * r, gz * r)
