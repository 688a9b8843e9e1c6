# SPDX-License-Identifier: Apache-2.0
"""Warp kernels for :func:`wtopo.pixel_terms.pixel_terms`: the fit's per-pixel normal, distortion and mask terms
in one pass over the rendered maps.

Forward: a thread takes a run of ``run`` pixels of one row (``offset`` counts runs, so a CPU launch splits into
chunks across threads) and writes the run's four partial sums: the normal term's numerator
``sum(alpha - <n_rendered, n_depth>)`` and pixel count over the pixels with a depth normal, the distortion sum,
and the mask's binary cross-entropy sum. Backward: the same runs turn the seeds of their sums into the gradients of
the rendered normal, opacity and distortion of their pixels. Every thread writes its own outputs (no atomics): CPU
and CUDA add the same terms in the same order.
"""

from typing import Any

import warp as wp

from .depth_normals import depth_normal


@wp.kernel
def pixel_terms_kernel(
    offset: int,
    normal: wp.array2d[Any],
    alpha: wp.array2d[Any],
    median: wp.array2d[Any],
    dist: wp.array2d[Any],
    origins: wp.array2d[Any],
    dirs: wp.array2d[Any],
    valid: wp.array2d[wp.uint8],
    target: wp.array2d[Any],
    has_target: int,
    lo: Any,
    hi: Any,
    eps: Any,
    run: int,
    sums: wp.array2d[Any],
    depth_normals: wp.array2d[Any],
):
    """Run ``r = offset + tid`` (row ``r // runs``, pixels ``run * (r % runs) ...`` of it, ``runs`` per row):
    ``sums[r] = (sum over the run's pixels with a depth normal of alpha - <normal, n_depth>, their count,
    sum of dist, sum of -(m log a + (1 - m) log(1 - a)) with a = clamp(alpha, lo, hi) and m = target when
    has_target, else 0)``; ``depth_normals[y, x]`` the depth normal of ``median`` (zero where there is none: see
    ``kernels/depth_normals.py``, ``valid`` the pixels whose depth counts)."""
    h = alpha.shape[0]
    w = alpha.shape[1]
    runs = (w + run - 1) // run
    r = offset + wp.tid()
    y = r // runs
    x0 = (r - y * runs) * run
    x1 = wp.min(x0 + run, w)
    zero = lo * type(lo)(0.0)
    one = type(lo)(1.0)
    num = zero
    count = zero
    dsum = zero
    bce = zero
    for x in range(x0, x1):
        n, ok = depth_normal(median, origins, dirs, valid, eps, y, x, h, w)
        depth_normals[y, x] = n
        if ok != wp.uint8(0):
            num += alpha[y, x] - wp.dot(normal[y, x], n)
            count += one
        dsum += dist[y, x]
        if has_target != 0:
            a = wp.clamp(alpha[y, x], lo, hi)
            m = target[y, x]
            bce -= m * wp.log(a) + (one - m) * wp.log(one - a)
    sums[r, 0] = num
    sums[r, 1] = count
    sums[r, 2] = dsum
    sums[r, 3] = bce


@wp.kernel
def pixel_terms_backward_kernel(
    offset: int,
    alpha: wp.array2d[Any],
    target: wp.array2d[Any],
    depth_normals: wp.array2d[Any],
    sums_grad: wp.array2d[Any],
    has_target: int,
    lo: Any,
    hi: Any,
    run: int,
    want_normal: int,
    want_alpha: int,
    want_dist: int,
    normal_grad: wp.array2d[Any],
    alpha_grad: wp.array2d[Any],
    dist_grad: wp.array2d[Any],
):
    """Run ``r = offset + tid`` as in :func:`pixel_terms_kernel`; with ``g`` the seed of its sums, each of its
    pixels gets ``normal_grad = -g[0] n_depth`` (the opacity in the numerator and the count are held fixed),
    ``dist_grad = g[2]``, ``alpha_grad = g[3] ((1 - m) / (1 - a) - m / a)`` where ``lo <= alpha <= hi`` (0
    outside: the clamp), each written where wanted."""
    w = alpha.shape[1]
    runs = (w + run - 1) // run
    r = offset + wp.tid()
    y = r // runs
    x0 = (r - y * runs) * run
    x1 = wp.min(x0 + run, w)
    g_normal = -sums_grad[r, 0]
    g_dist = sums_grad[r, 2]
    g_bce = sums_grad[r, 3]
    zero = lo * type(lo)(0.0)
    one = type(lo)(1.0)
    for x in range(x0, x1):
        if want_normal != 0:
            normal_grad[y, x] = depth_normals[y, x] * g_normal
        if want_dist != 0:
            dist_grad[y, x] = g_dist
        if want_alpha != 0:
            g = zero
            a = alpha[y, x]
            if has_target != 0 and a >= lo and a <= hi:
                m = target[y, x]
                g = g_bce * ((one - m) / (one - a) - m / a)
            alpha_grad[y, x] = g
