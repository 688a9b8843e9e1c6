# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of the fused photometric loss: per-pixel L1 and SSIM maps with a separable Gaussian window.

Images are ``[H, W, C]`` arrays; the SSIM statistics are taken over the ``valid`` window positions
(``Hv = H - win + 1`` by ``Wv = W - win + 1``), as :func:`wtopo.metrics.ssim` does. The forward is
two 1-D passes: :func:`ssim_rows_kernel` blurs the five moments ``(x, y, x^2, y^2, x y)`` along
rows (and writes ``|x - y|``), :func:`ssim_map_kernel` blurs them along columns and evaluates SSIM
and its partial derivatives w.r.t. the blurred ``x``, ``x^2`` and ``x y`` (``y`` is the target, not
differentiated). The adjoint is the transpose of the two passes (:func:`ssim_adjoint_columns_kernel`
then :func:`photometric_grad_kernel`), then the chain rule through the moments. Every kernel
writes disjoint outputs (no atomics): CPU and CUDA give the same sums in the same order.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})  # explicit adjoint kernels below

vec5f = wp.types.vector(length=5, dtype=wp.float32)
vec5d = wp.types.vector(length=5, dtype=wp.float64)


@wp.kernel
def ssim_rows_kernel(
    x: wp.array3d[Any],
    y: wp.array3d[Any],
    window: wp.array[Any],
    rows: wp.array3d[Any],
    l1: wp.array3d[Any],
):
    """``|x - y|`` at every element and, for the first ``Wv`` columns, the row-blurred five moments."""
    i, j, c = wp.tid()
    a = x[i, j, c]
    b = y[i, j, c]
    l1[i, j, c] = wp.abs(a - b)
    if j >= rows.shape[1]:
        return
    zero = type(a)(0.0)
    m = wp.vector(zero, zero, zero, zero, zero)
    for t in range(window.shape[0]):
        p = x[i, j + t, c]
        q = y[i, j + t, c]
        m = m + window[t] * wp.vector(p, q, p * p, q * q, p * q)
    rows[i, j, c] = m


@wp.kernel
def ssim_map_kernel(
    rows: wp.array3d[Any],
    window: wp.array[Any],
    c1: Any,
    c2: Any,
    ssim: wp.array3d[Any],
    partials: wp.array3d[Any],
):
    """Column blur of the row moments, SSIM at one valid position, and ``dS / d(mx, E[x^2], E[xy])``."""
    i, j, c = wp.tid()
    zero = type(c1)(0.0)
    m = wp.vector(zero, zero, zero, zero, zero)
    for t in range(window.shape[0]):
        m = m + window[t] * rows[i + t, j, c]
    mx = m[0]
    my = m[1]
    sxx = m[2] - mx * mx
    syy = m[3] - my * my
    sxy = m[4] - mx * my
    two = type(c1)(2.0)
    a1 = two * mx * my + c1
    a2 = two * sxy + c2
    b1 = mx * mx + my * my + c1
    b2 = sxx + syy + c2
    s = (a1 * a2) / (b1 * b2)
    ssim[i, j, c] = s
    # E[x^2] and E[xy] enter only through sxx and sxy; mx directly and through both
    d_exx = -s / b2
    d_exy = two * a1 / (b1 * b2)
    d_mx = two * my * a2 / (b1 * b2) - two * mx * s / b1 - two * mx * d_exx - my * d_exy
    partials[i, j, c] = wp.vector(d_mx, d_exx, d_exy)


@wp.kernel
def ssim_adjoint_columns_kernel(
    partials: wp.array3d[Any],
    g_ssim: wp.array3d[Any],
    window: wp.array[Any],
    cols: wp.array3d[Any],
):
    """Transpose of the column blur: ``cols[i, j] = sum_t w[t] g[i - t, j] partials[i - t, j]`` over valid rows."""
    i, j, c = wp.tid()
    zero = window[0] * type(window[0])(0.0)
    acc = wp.vector(zero, zero, zero)
    hv = partials.shape[0]
    for t in range(window.shape[0]):
        r = i - t
        if r >= 0 and r < hv:
            acc = acc + (window[t] * g_ssim[r, j, c]) * partials[r, j, c]
    cols[i, j, c] = acc


@wp.kernel
def photometric_grad_kernel(
    x: wp.array3d[Any],
    y: wp.array3d[Any],
    cols: wp.array3d[Any],
    g_l1: wp.array3d[Any],
    window: wp.array[Any],
    grad: wp.array3d[Any],
):
    """Transpose of the row blur and the chain rule through the moments, plus the L1 term: ``d loss / d x``."""
    i, j, c = wp.tid()
    a = x[i, j, c]
    b = y[i, j, c]
    zero = type(a)(0.0)
    wv = cols.shape[1]
    acc = wp.vector(zero, zero, zero)
    for t in range(window.shape[0]):
        q = j - t
        if q >= 0 and q < wv:
            acc = acc + window[t] * cols[i, q, c]
    d = a - b
    sign = zero
    if d > zero:
        sign = type(a)(1.0)
    elif d < zero:
        sign = type(a)(-1.0)
    # x enters the moments as x (mx), x^2 (E[x^2]) and x y (E[xy])
    grad[i, j, c] = grad[i, j, c] + acc[0] + type(a)(2.0) * a * acc[1] + b * acc[2] + g_l1[i, j, c] * sign


# explicit float32 / float64 overloads: one compile of the module with both
for _s, _v3, _v5 in ((wp.float32, wp.vec3, vec5f), (wp.float64, wp.vec3d, vec5d)):
    _a = wp.array3d(dtype=_s)
    _w = wp.array(dtype=_s)
    wp.overload(ssim_rows_kernel, {"x": _a, "y": _a, "window": _w, "rows": wp.array3d(dtype=_v5), "l1": _a})
    wp.overload(ssim_map_kernel, {"rows": wp.array3d(dtype=_v5), "window": _w, "c1": _s, "c2": _s, "ssim": _a,
                                  "partials": wp.array3d(dtype=_v3)})
    wp.overload(ssim_adjoint_columns_kernel, {"partials": wp.array3d(dtype=_v3), "g_ssim": _a, "window": _w,
                                              "cols": wp.array3d(dtype=_v3)})
    wp.overload(photometric_grad_kernel, {"x": _a, "y": _a, "cols": wp.array3d(dtype=_v3), "g_l1": _a,
                                          "window": _w, "grad": _a})
