# SPDX-License-Identifier: Apache-2.0
"""Discrete kernels of the surfel rasterizer: screen bounds, tile intersections, tile ranges.

Bounds are computed in float64 whatever the op dtype. A surfel's footprint is the union of

* the 3D disk ``u^2 + v^2 <= rr`` in its plane, where ``rr = 2 ln(255 opacity)`` is the exponent at
  which ``opacity * exp(-rr / 2) = 1/255`` (no pixel outside it can pass the alpha threshold);
  its image is bounded with the dual conic of the disk in undistorted normalised coordinates and
  mapped to tiles through per-tile-column / per-tile-row tables of the pixel rays' normalised
  coordinates (so any lens model that :meth:`wtopo.Camera.pixel_rays` encodes is handled); a disk
  reaching the camera plane has an unbounded image and covers every tile;
* the screen-space filter disk ``|pixel - centre|^2 / sigma^2 <= rr`` around the projected centre
  (``1 / sigma^2`` is the camera record's ``filter_inv_sq``).

The pairs are written in the surfels' depth order and sorted by tile alone (int32 keys, a stable radix sort of
the tile's bits), which keeps every tile's list front to back.

Tile counts are therefore bounded by the number of tiles whatever the scale.
"""

from typing import Any

import warp as wp

from .rasterize import (
    ALPHA_MIN,
    QUAT_MIN_SQ,
    SCALE_MIN,
    cam_point,
    project_pixel,
)
from .rasterize_records import declare_float_overloads
from .rotation import quat_axes

wp.set_module_options({"enable_backward": False})

RR_REL_MARGIN = 1.0e-4  # widen the cutoff exponent so the bound stays conservative under rounding
PIXEL_MARGIN = 1.0e-3  # pixels added to the filter-disk radius for the same reason
RADIUS_CAP = 1.0e9  # radii are clamped before the int conversion (no overflow for huge surfels)


@wp.func
def first_at_least(table: wp.array[wp.float64], value: wp.float64):
    """Index of the first entry >= value in a non-decreasing table (len if none)."""
    lo = int(0)
    hi = table.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if table[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def last_at_most(table: wp.array[wp.float64], value: wp.float64):
    """Index of the last entry <= value in a non-decreasing table (-1 if none)."""
    lo = int(0)
    hi = table.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if table[mid] <= value:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@wp.func
def cam_rotate64(cam: Any, v: wp.vec3d):
    """World-to-camera rotation of a :class:`~wtopo.kernels.rasterize.CameraRecord` applied to a float64 vector."""
    R = cam.R
    return wp.vec3d(
        wp.float64(R[0, 0]) * v[0] + wp.float64(R[0, 1]) * v[1] + wp.float64(R[0, 2]) * v[2],
        wp.float64(R[1, 0]) * v[0] + wp.float64(R[1, 1]) * v[1] + wp.float64(R[1, 2]) * v[2],
        wp.float64(R[2, 0]) * v[0] + wp.float64(R[2, 1]) * v[1] + wp.float64(R[2, 2]) * v[2],
    )


@wp.func
def pixel_to_tile_range(center: wp.float64, radius: wp.float64, size: int, tile_size: int):
    """Tiles [lo, hi] covering pixel centres within ``radius`` of ``center`` (lo > hi: none)."""
    lo_f = wp.ceil(center - radius - wp.float64(0.5))
    hi_f = wp.floor(center + radius - wp.float64(0.5))
    lo_f = wp.max(lo_f, wp.float64(0.0))
    hi_f = wp.min(hi_f, wp.float64(size - 1))
    if lo_f > hi_f:
        return 1, 0
    return int(lo_f) // tile_size, int(hi_f) // tile_size


@wp.func
def rect_union(ax0: int, ax1: int, ay0: int, ay1: int, bx0: int, bx1: int, by0: int, by1: int, nx: int, ny: int):
    """Bounding box ``x0, x1, y0, y1`` (inclusive) of two inclusive boxes, either possibly empty (lo > hi);
    ``nx, -1, ny, -1`` when both are."""
    x0 = nx
    x1 = int(-1)
    y0 = ny
    y1 = int(-1)
    if ax0 <= ax1 and ay0 <= ay1:
        x0 = ax0
        x1 = ax1
        y0 = ay0
        y1 = ay1
    if bx0 <= bx1 and by0 <= by1:
        x0 = wp.min(x0, bx0)
        x1 = wp.max(x1, bx1)
        y0 = wp.min(y0, by0)
        y1 = wp.max(y1, by1)
    return x0, x1, y0, y1


@wp.kernel
def bin_surfels_kernel(
    offset: int,
    means: wp.array[Any],
    quats: wp.array[Any],
    scales: wp.array[Any],
    opacities: wp.array[Any],
    cams: wp.array[Any],
    colx_min: wp.array[wp.float64],
    colx_max: wp.array[wp.float64],
    rowy_min: wp.array[wp.float64],
    rowy_max: wp.array[wp.float64],
    pxcol_min: wp.array[wp.float64],
    pxcol_max: wp.array[wp.float64],
    pxrow_min: wp.array[wp.float64],
    pxrow_max: wp.array[wp.float64],
    tile_size: int,
    rect: wp.array[wp.vec4i],
    counts: wp.array[wp.int32],
    radii: wp.array[wp.int32],
    means2d: wp.array[Any],
    cutoff: wp.array[Any],
    prect: wp.array[wp.vec4i],
    zc: wp.array[Any],
):
    """Tile rectangle, tile count, pixel radius, projected centre, pixel rectangle and depth of one surfel.

    ``prect`` is the same bound at pixel granularity (``px*`` tables: one entry per pixel column / row),
    ``[x0, y0, x1, y1)``, empty where the surfel covers no tile: the CPU tile kernels
    (``kernels/rasterize_tiles.py``) visit only its pixels. ``zc`` is the centre's z-depth, ``+inf``
    for a culled surfel (the depth order of the binning's sort keys).
    """
    cam = cams[0]
    i = wp.tid() + offset
    width = cam.width
    height = cam.height
    p = means[i]
    x0c = p[0]
    rect[i] = wp.vec4i(0, 0, 0, 0)
    counts[i] = 0
    radii[i] = 0
    means2d[i] = wp.vector(type(x0c)(0.0), type(x0c)(0.0))
    cutoff[i] = type(x0c)(-1.0)
    prect[i] = wp.vec4i(0, 0, 0, 0)
    zc[i] = type(x0c)(wp.inf)
    pc_op = cam_point(cam, p)
    op = wp.float64(opacities[i])
    near = wp.float64(cam.near)
    pcz = wp.float64(pc_op[2])
    if op < wp.float64(ALPHA_MIN) or not (pcz > near):
        return
    m2 = project_pixel(cam, pc_op)
    means2d[i] = m2
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    rr = wp.float64(2.0) * wp.log(wp.float64(255.0) * op)
    rr = rr * wp.float64(1.0 + RR_REL_MARGIN) + wp.float64(1.0e-6)
    cutoff[i] = type(x0c)(rr)  # pixel kernels skip rho > cutoff without evaluating exp
    # screen-space filter disk
    r2d = wp.sqrt(rr / wp.float64(cam.filter_inv_sq)) + wp.float64(PIXEL_MARGIN)
    ax0, ax1 = pixel_to_tile_range(wp.float64(m2[0]), r2d, width, tile_size)
    ay0, ay1 = pixel_to_tile_range(wp.float64(m2[1]), r2d, height, tile_size)
    apx0, apx1 = pixel_to_tile_range(wp.float64(m2[0]), r2d, width, 1)
    apy0, apy1 = pixel_to_tile_range(wp.float64(m2[1]), r2d, height, 1)
    radius = r2d
    # 3D disk: dual conic C* = h0 h0^T + h1 h1^T - h2 h2^T of the disk's image
    q = quats[i]
    q64 = wp.vec4d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]), wp.float64(q[3]))
    tu, tv, n = quat_axes(q64, QUAT_MIN_SQ)
    sc = scales[i]
    r = wp.sqrt(rr)
    su = wp.max(wp.float64(sc[0]), wp.float64(SCALE_MIN))
    sv = wp.max(wp.float64(sc[1]), wp.float64(SCALE_MIN))
    h0 = cam_rotate64(cam, tu) * (r * su)
    h1 = cam_rotate64(cam, tv) * (r * sv)
    h2 = wp.vec3d(wp.float64(pc_op[0]), wp.float64(pc_op[1]), pcz)
    ext_z = wp.sqrt(h0[2] * h0[2] + h1[2] * h1[2])
    bx0 = int(0)
    bx1 = tiles_x - 1
    by0 = int(0)
    by1 = tiles_y - 1
    bpx0 = int(0)
    bpx1 = width - 1
    bpy0 = int(0)
    bpy1 = height - 1
    full = True
    if pcz > ext_z:
        c22 = ext_z * ext_z - pcz * pcz
        c00 = h0[0] * h0[0] + h1[0] * h1[0] - h2[0] * h2[0]
        c11 = h0[1] * h0[1] + h1[1] * h1[1] - h2[1] * h2[1]
        c02 = h0[0] * h0[2] + h1[0] * h1[2] - h2[0] * h2[2]
        c12 = h0[1] * h0[2] + h1[1] * h1[2] - h2[1] * h2[2]
        xc = c02 / c22
        yc = c12 / c22
        hx = wp.sqrt(wp.max(xc * xc - c00 / c22, wp.float64(0.0)))
        hy = wp.sqrt(wp.max(yc * yc - c11 / c22, wp.float64(0.0)))
        if wp.isfinite(xc) and wp.isfinite(yc) and wp.isfinite(hx) and wp.isfinite(hy):
            full = False
            bx0 = first_at_least(colx_max, xc - hx)
            bx1 = last_at_most(colx_min, xc + hx)
            by0 = first_at_least(rowy_max, yc - hy)
            by1 = last_at_most(rowy_min, yc + hy)
            bpx0 = first_at_least(pxcol_max, xc - hx)
            bpx1 = last_at_most(pxcol_min, xc + hx)
            bpy0 = first_at_least(pxrow_max, yc - hy)
            bpy1 = last_at_most(pxrow_min, yc + hy)
            radius = wp.max(radius, wp.max(hx * wp.float64(cam.fx), hy * wp.float64(cam.fy)))
    if full:
        radius = wp.float64(wp.max(width, height))
    # union of the two rectangles (either may be empty), in tiles and in pixels
    x0, x1, y0, y1 = rect_union(ax0, ax1, ay0, ay1, bx0, bx1, by0, by1, tiles_x, tiles_y)
    if x0 > x1 or y0 > y1:
        return
    qx0, qx1, qy0, qy1 = rect_union(apx0, apx1, apy0, apy1, bpx0, bpx1, bpy0, bpy1, width, height)
    if qx0 <= qx1 and qy0 <= qy1:
        prect[i] = wp.vec4i(qx0, qy0, qx1 + 1, qy1 + 1)
    zc[i] = pc_op[2]
    rect[i] = wp.vec4i(x0, y0, x1 + 1, y1 + 1)
    counts[i] = (x1 + 1 - x0) * (y1 + 1 - y0)
    radii[i] = int(wp.ceil(wp.min(radius, wp.float64(RADIUS_CAP))))


@wp.kernel
def emit_intersections_kernel(
    offset: int,
    order: wp.array[wp.int32],
    rect: wp.array[wp.vec4i],
    offsets: wp.array[wp.int32],
    tiles_x: int,
    capacity: int,
    keys: wp.array[wp.int32],
    values: wp.array[wp.int32],
):
    """Write one ``(tile, surfel)`` pair per tile a surfel's rectangle covers, the surfels in depth order.

    Thread ``j`` takes surfel ``order[j]`` (the ``j``-th nearest) and writes from ``offsets[j]`` (the exclusive
    sum of the tile counts in that order), so the pairs are laid out in depth order and a stable sort by tile
    alone leaves each tile's list front to back. Pairs at or beyond ``capacity`` are dropped (the caller sized
    the buffers from an earlier count and reports the overflow; the buffers hold ``2 * capacity`` entries for
    the radix sort): with the surfels in depth order those are the farthest ones.
    """
    j = wp.tid() + offset
    i = order[j]
    r = rect[i]
    k = offsets[j]
    for ty in range(r[1], r[3]):
        for tx in range(r[0], r[2]):
            if k < capacity:
                keys[k] = ty * tiles_x + tx
                values[k] = i
            k += 1


@wp.kernel
def tile_ranges_kernel(
    offset: int,
    keys: wp.array[wp.int32],
    count: int,
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
):
    """Start and end of each tile's run in the sorted intersection list (empty tiles stay 0, 0).

    Keys of ``tile_start.shape[0]`` or more are padding (sorted after every real pair) and are ignored.
    """
    k = wp.tid() + offset
    tile = keys[k]
    if tile >= tile_start.shape[0]:
        return
    if k == 0:  # noqa: SIM114  Warp's `or` does not short-circuit: it would read keys[-1]
        tile_start[tile] = k
    elif keys[k - 1] != tile:
        tile_start[tile] = k
    if k == count - 1:  # noqa: SIM114  Warp's `or` does not short-circuit: it would read keys[count]
        tile_end[tile] = k + 1
    elif keys[k + 1] != tile:
        tile_end[tile] = k + 1


@wp.kernel
def sum_visibility_kernel(offset: int, per_worker: wp.array2d[wp.int32], visibility: wp.array[wp.int32]):
    """Sum the per-worker pixel counts of one surfel."""
    i = wp.tid() + offset
    total = int(0)
    for w in range(per_worker.shape[0]):
        total += per_worker[w, i]
    visibility[i] = total


# one compile of this module with every overload (see kernels/rasterize_records.py)
declare_float_overloads(bin_surfels_kernel)
