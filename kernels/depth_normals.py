# SPDX-License-Identifier: Apache-2.0
"""Warp kernel for :func:`wtopo.depth_normals.depth_normals`: normals of a depth map by central differences.

A thread takes a run of pixels in row-major order (one on CUDA); ``offset`` counts runs, so a CPU launch
splits into chunks across threads. Forward only: the fit uses these normals as a detached target (2DGS's normal
consistency with the depth normal held fixed), so nothing is differentiated through them.
"""

from typing import Any

import warp as wp


@wp.func
def _pixel(depth: wp.array2d[Any], origins: wp.array2d[Any], dirs: wp.array2d[Any], valid: wp.array2d[wp.uint8],
           eps: Any, y: int, x: int, h: int, w: int, normals: wp.array2d[Any], mask: wp.array2d[wp.uint8]):
    d0 = dirs[y, x]
    n = d0 * type(eps)(0.0)
    ok = wp.uint8(0)
    inner = y >= 1 and x >= 1 and y < h - 1 and x < w - 1
    if inner and (valid[y, x] != wp.uint8(0) and valid[y, x - 1] != wp.uint8(0) and valid[y, x + 1] != wp.uint8(0)
                  and valid[y - 1, x] != wp.uint8(0) and valid[y + 1, x] != wp.uint8(0)):
        right = origins[y, x + 1] + dirs[y, x + 1] * depth[y, x + 1]
        left = origins[y, x - 1] + dirs[y, x - 1] * depth[y, x - 1]
        down = origins[y + 1, x] + dirs[y + 1, x] * depth[y + 1, x]
        up = origins[y - 1, x] + dirs[y - 1, x] * depth[y - 1, x]
        c = wp.cross(right - left, down - up)
        ln = wp.length(c)
        if ln > eps:  # False for NaN too
            n = c / ln
            if wp.dot(n, d0) > type(eps)(0.0):
                n = -n
            ok = wp.uint8(1)
    normals[y, x] = n
    mask[y, x] = ok


@wp.kernel
def depth_normals_kernel(
    offset: int,
    depth: wp.array2d[Any],
    origins: wp.array2d[Any],
    dirs: wp.array2d[Any],
    valid: wp.array2d[wp.uint8],
    eps: Any,
    per_thread: int,
    normals: wp.array2d[Any],
    mask: wp.array2d[wp.uint8],
):
    """Pixels ``offset + tid * per_thread ...`` (row-major, ``y W + x``; fewer at the end), each: the unit
    normal of ``cross(p[y, x+1] - p[y, x-1], p[y+1, x] - p[y-1, x])`` with ``p = origin + dir * depth``,
    turned against the pixel's ray, and mask 1; zero and mask 0 on the border, where the pixel or one of its
    four neighbours is not ``valid``, or where the cross product is not longer than ``eps``. Several pixels
    per thread on the CPU (a thread costs more there than the pixel), one on CUDA."""
    h = depth.shape[0]
    w = depth.shape[1]
    start = (offset + wp.tid()) * per_thread
    end = wp.min(start + per_thread, h * w)
    for i in range(start, end):
        y = i // w
        _pixel(depth, origins, dirs, valid, eps, y, i - y * w, h, w, normals, mask)


# explicit float32 / float64 overloads, launched as such: {scalar: kernel}
OVERLOADS = {}
for _s, _v3 in ((wp.float32, wp.vec3), (wp.float64, wp.vec3d)):
    _n = wp.array2d(dtype=_v3)
    _u = wp.array2d(dtype=wp.uint8)
    OVERLOADS[_s] = wp.overload(depth_normals_kernel, {
        "offset": int, "depth": wp.array2d(dtype=_s), "origins": _n, "dirs": _n, "valid": _u, "eps": _s,
        "per_thread": int, "normals": _n, "mask": _u})
