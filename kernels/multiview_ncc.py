# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of the multi-view window cost: patch NCC through the rendered plane into neighbouring views.

One thread per reference window (centre pixel ``(py, px)``, ``(2 half + 1)^2`` pixels). The window's
plane is the rendered one at its centre (z-depth ``d``, normal ``n``); each window pixel's ray (from the
reference centre ``c``, direction ``dq``) meets it at ``c + t dq`` with ``t = d <dp, n> / <dq, n>``
(``dp``: the centre pixel's ray), which lands in a source camera at ``o_s + t R_s dq`` (``o_s = R_s c + t_s``).
It is projected with the source's pinhole and OpenCV distortion, sampled bilinearly from the source's
grey image exactly as ``torch.nn.functional.grid_sample(mode="bilinear", padding_mode="border",
align_corners=False)`` does, and the window's NCC is taken against the reference window (grey levels
centred on the reference window's mean, its variance given). ``cost = clamp(1 - NCC, 0, 2)``, 2 when a
window point falls behind or outside the source; each window keeps the smaller cost of its (one or two)
sources. Windows that do not count (depth not positive, untextured, uncovered, grazing) are not scored:
cost 2, no gradient.

:func:`window_costs_kernel` writes the cost, whether the window counts, and per source the statistics
the adjoint needs (the source window's mean, the NCC numerator, its denominator, and the source's share
of the gradient: torch's ``amin`` splits it evenly between equal costs; 0 where the cost is clamped or
constant). :func:`window_costs_adjoint_kernel` replays each window once per source with a share and
writes ``d cost / d depth`` and ``d cost / d normal`` of the window; :func:`scatter_window_grads_kernel`
adds them at the windows' centre pixels with atomics (several windows may share a centre). The first two
write one window per thread, so their launches may be split across CPU threads. Source parameters are one
row per source, see :data:`PARAMS`.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})  # explicit adjoint kernel below

PARAMS = 23
"""Values per source row: R (9, row-major), o = R c + t (3), fx, skew, cx, fy, cy, k1, k2, p1, p2, k3,
whether the lens is distorted (1 or 0). The source's size is its image's."""


@wp.func
def _row(params: wp.array2d[Any], s: int, i: int):
    return wp.vector(params[s, i], params[s, i + 1], params[s, i + 2])


@wp.func
def _intrinsics(params: wp.array2d[Any], s: int):
    """Source ``s``'s (fx, skew, cx, fy, cy), its (k1, k2, p1, p2, k3) and whether it is distorted."""
    k = wp.vector(params[s, 12], params[s, 13], params[s, 14], params[s, 15], params[s, 16])
    lens = wp.vector(params[s, 17], params[s, 18], params[s, 19], params[s, 20], params[s, 21])
    distorted = int(0)
    if params[s, 22] != params[s, 22] * type(params[s, 22])(0.0):
        distorted = 1
    return k, lens, distorted


@wp.func
def _distort(lens: Any, xn: Any, yn: Any):
    """Distorted normalised coordinates and the Jacobian ``d(xd, yd) / d(xn, yn)`` as four scalars."""
    one = type(xn)(1.0)
    two = type(xn)(2.0)
    k1 = lens[0]
    k2 = lens[1]
    p1 = lens[2]
    p2 = lens[3]
    k3 = lens[4]
    r2 = xn * xn + yn * yn
    radial = one + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + two * p1 * xn * yn + p2 * (r2 + two * xn * xn)
    yd = yn * radial + p1 * (r2 + two * yn * yn) + two * p2 * xn * yn
    dr = k1 + r2 * (two * k2 + type(xn)(3.0) * k3 * r2)  # d radial / d r2
    j00 = radial + two * xn * xn * dr + two * p1 * yn + type(xn)(6.0) * p2 * xn
    j01 = two * xn * yn * dr + two * p1 * xn + two * p2 * yn
    j10 = two * xn * yn * dr + two * p1 * xn + two * p2 * yn
    j11 = radial + two * yn * yn * dr + type(xn)(6.0) * p1 * yn + two * p2 * xn
    return xd, yd, j00, j01, j10, j11


@wp.func
def _clip(u: Any, size: int):
    """grid_sample's source index of pixel coordinate ``u`` (align_corners=False, border padding: torch's
    ``((u / size * 2 - 1 + 1) size - 1) / 2``, here ``u - 1/2``, equal up to round-off) and its derivative
    (1 inside, 0 where clipped, as torch's ``clip_coordinates_set_grad``)."""
    zero = type(u)(0.0)
    i = u - type(u)(0.5)
    top = type(u)(float(size - 1))
    if i <= zero:
        return zero, zero
    if i >= top:
        return top, zero
    return i, type(u)(1.0)


@wp.func
def _sample(img: wp.array2d[Any], u: Any, v: Any):
    """Bilinear grey level at pixel coordinates ``(u, v)`` (centres at +0.5) and its derivatives in ``u``, ``v``."""
    ix, mx = _clip(u, img.shape[1])
    iy, my = _clip(v, img.shape[0])
    x0 = int(ix)  # the clipped index is >= 0: truncation is the floor
    y0 = int(iy)
    one = type(u)(1.0)
    e = ix - type(u)(float(x0))  # weight of the right column
    w = iy - type(u)(float(y0))  # weight of the lower row
    # grid_sample reads 0 beyond the last row / column; its weight there is 0 (the index was clipped to the
    # last pixel centre, where the derivative is 0 too), so reading the last pixel again changes nothing
    x1 = wp.min(x0 + 1, img.shape[1] - 1)
    y1 = wp.min(y0 + 1, img.shape[0] - 1)
    a = img[y0, x0]
    b = img[y0, x1]
    c = img[y1, x0]
    f = img[y1, x1]
    val = (a * (one - e) + b * e) * (one - w) + (c * (one - e) + f * e) * w
    du = ((b - a) * (one - w) + (f - c) * w) * mx
    dv = ((c - a) * (one - e) + (f - b) * e) * my
    return val, du, dv


@wp.func
def _sample_value(img: wp.array2d[Any], u: Any, v: Any):
    """:func:`_sample`'s grey level alone (the forward pass)."""
    ix, mx = _clip(u, img.shape[1])
    iy, my = _clip(v, img.shape[0])
    x0 = int(ix)
    y0 = int(iy)
    one = type(u)(1.0)
    e = ix - type(u)(float(x0))
    w = iy - type(u)(float(y0))
    x1 = wp.min(x0 + 1, img.shape[1] - 1)
    y1 = wp.min(y0 + 1, img.shape[0] - 1)
    return (img[y0, x0] * (one - e) + img[y0, x1] * e) * (one - w) + (img[y1, x0] * (one - e) + img[y1, x1] * e) * w


@wp.func
def _project_value(p: Any, k: Any, lens: Any, distorted: int):
    """:func:`_project`'s pixel ``(u, v)`` alone (the forward pass)."""
    z = p[2]
    zs = z
    if wp.abs(z) < type(z)(1e-12):
        zs = type(z)(1e-12)
    xn = p[0] / zs
    yn = p[1] / zs
    if distorted != 0:
        xd, yd, j00, j01, j10, j11 = _distort(lens, xn, yn)
        xn = xd
        yn = yd
    return k[0] * xn + k[1] * yn + k[2], k[3] * yn + k[4]


@wp.func
def _project(p: Any, k: Any, lens: Any, distorted: int):
    """Pixel ``(u, v)``, z-depth and ``d(u, v) / d p`` (two rows) of a point ``p`` in the source's frame
    (``k``: fx, skew, cx, fy, cy; ``lens``: k1, k2, p1, p2, k3, applied when ``distorted``)."""
    z = p[2]
    tiny = type(z)(1e-12)  # TorchCam.project_camera's guard against z = 0
    zs = z
    live = type(z)(1.0)  # torch.where passes no gradient to z where it substitutes the guard
    if wp.abs(z) < tiny:
        zs = tiny
        live = type(z)(0.0)
    xn = p[0] / zs
    yn = p[1] / zs
    xd = xn
    yd = yn
    j00 = type(z)(1.0)
    j01 = type(z)(0.0)
    j10 = type(z)(0.0)
    j11 = type(z)(1.0)
    if distorted != 0:
        xd, yd, j00, j01, j10, j11 = _distort(lens, xn, yn)
    fx = k[0]
    sk = k[1]
    fy = k[3]
    u = fx * xd + sk * yd + k[2]
    v = fy * yd + k[4]
    # d(u, v)/d(xn, yn), then through xn = p0 / z, yn = p1 / z
    ux = fx * j00 + sk * j10
    uy = fx * j01 + sk * j11
    vx = fy * j10
    vy = fy * j11
    du = wp.vector(ux / zs, uy / zs, -(ux * xn + uy * yn) / zs * live)
    dv = wp.vector(vx / zs, vy / zs, -(vx * xn + vy * yn) / zs * live)
    return u, v, z, du, dv


@wp.func
def _ray_param(dq: Any, n: Any, dn: Any):
    """``t = dn / <dq, n>`` with the denominator kept off zero as the torch term does, and whether it was."""
    den = wp.dot(dq, n)
    tiny = type(dn)(1e-8)
    live = type(dn)(1.0)
    if wp.abs(den) < tiny:
        den = tiny
        live = type(dn)(0.0)
    return dn / den, den, live


@wp.func
def _source_cost(img: wp.array2d[Any], params: wp.array2d[Any], s: int, y: int, x: int, half: int, n: Any,
                 dn: Any, dirs: wp.array2d[Any], gray: wp.array2d[Any], mref: Any, rvar: Any, eps: Any):
    """``clamp(1 - NCC, 0, 2)`` of the window against source ``s`` (2 where a point leaves it) and
    ``(source window mean, NCC numerator, NCC denominator, 1 where the cost passes a gradient)``."""
    zero = type(dn)(0.0)
    two = type(dn)(2.0)
    side = 2 * half + 1
    kk = side * side
    r0 = _row(params, s, 0)
    r1 = _row(params, s, 3)
    r2 = _row(params, s, 6)
    o = _row(params, s, 9)
    kk5, lens, distorted = _intrinsics(params, s)
    w_img = type(dn)(float(img.shape[1]))
    h_img = type(dn)(float(img.shape[0]))
    inside = int(1)
    shift = zero
    sum_r = zero
    sum_e = zero
    sum_ee = zero
    sum_re = zero
    for k in range(kk):
        qy = y + k // side - half
        qx = x + k % side - half
        dq = dirs[qy, qx]
        t, den, kept = _ray_param(dq, n, dn)
        p = o + t * wp.vector(wp.dot(r0, dq), wp.dot(r1, dq), wp.dot(r2, dq))
        u, v = _project_value(p, kk5, lens, distorted)
        if not (p[2] > zero and u >= zero and u <= w_img and v >= zero and v <= h_img):
            inside = 0
            break
        val = _sample_value(img, u, v)
        if k == 0:
            shift = val  # shifted sums: the window's variance without float32 cancellation
        e = val - shift
        r = gray[qy, qx] - mref
        sum_r += r
        sum_e += e
        sum_ee += e * e
        sum_re += r * e
    if inside == 0:
        return two, wp.vector(zero, zero, type(dn)(1.0), zero)
    inv = type(dn)(1.0) / type(dn)(float(kk))
    me = sum_e * inv
    var = wp.max(sum_ee * inv - me * me, zero)
    num = (sum_re - me * sum_r) * inv
    root = wp.sqrt(rvar * var + eps)
    c = type(dn)(1.0) - num / root
    live = type(dn)(1.0)
    if c < zero:
        c = zero
        live = zero
    if c > two:
        c = two
        live = zero
    return c, wp.vector(shift + me, num, root, live)


@wp.func
def _plane(depth: wp.array2d[Any], normal: wp.array2d[Any], dirs: wp.array2d[Any], y: int, x: int):
    """The window's plane: unit normal (the torch term's ``n / max(|n|, 1e-8)``), the raw normal's length,
    and ``d <dp, n>`` (the numerator of every window pixel's ray parameter)."""
    nr = normal[y, x]
    ln = wp.length(nr)
    n = nr / wp.max(ln, type(ln)(1e-8))
    return n, ln, depth[y, x] * wp.dot(dirs[y, x], n)


@wp.kernel
def window_costs_kernel(
    offset: int,
    depth: wp.array2d[Any],
    normal: wp.array2d[Any],
    alpha: wp.array2d[Any],
    py: wp.array[wp.int64],
    px: wp.array[wp.int64],
    gray: wp.array2d[Any],
    mean: wp.array2d[Any],
    var: wp.array2d[Any],
    dirs: wp.array2d[Any],
    length: wp.array2d[Any],
    img0: wp.array2d[Any],
    img1: wp.array2d[Any],
    params: wp.array2d[Any],
    sources: int,
    half: int,
    min_std: Any,
    grazing: Any,
    alpha_min: Any,
    eps: Any,
    cost: wp.array[Any],
    ok: wp.array[Any],
    stats: wp.array2d[Any],
):
    """Whether window ``i`` counts (positive depth, textured, covered, no window ray within ``grazing`` of the
    plane) and, if it does, its best cost over the sources and per source the adjoint's statistics
    (``i = offset + tid``: chunks of windows may run from several CPU threads, each thread writes window ``i``)."""
    i = offset + wp.tid()
    y = int(py[i])
    x = int(px[i])
    zero = min_std * type(min_std)(0.0)
    n, ln, dn = _plane(depth, normal, dirs, y, x)
    mref = mean[y, x]
    rvar = var[y, x]
    one = type(min_std)(1.0)
    ok[i] = zero
    cost[i] = type(min_std)(2.0)
    # a window that does not count is not scored (cost 2, no gradient): the term weights it out anyway
    stats[i, 0] = wp.vector(zero, zero, one, zero)
    stats[i, 1] = wp.vector(zero, zero, one, zero)
    if not (depth[y, x] > zero and wp.sqrt(rvar) >= min_std and alpha[y, x] >= alpha_min):
        return
    # the smallest |cos| between a window ray and the plane normal (rays are not unit: divide by length)
    side = 2 * half + 1
    low = type(min_std)(1.0e30)
    for k in range(side * side):
        qy = y + k // side - half
        qx = x + k % side - half
        low = wp.min(low, wp.abs(wp.dot(dirs[qy, qx], n) / length[qy, qx]))
    if not (low > grazing):
        return
    c0, s0 = _source_cost(img0, params, 0, y, x, half, n, dn, dirs, gray, mref, rvar, eps)
    best = c0
    share0 = type(min_std)(1.0)
    if sources > 1:
        c1, s1 = _source_cost(img1, params, 1, y, x, half, n, dn, dirs, gray, mref, rvar, eps)
        share1 = zero
        if c1 < c0:
            best = c1
            share0 = zero
            share1 = type(min_std)(1.0)
        elif c1 == c0:  # torch's amin splits the gradient evenly between equal values
            share0 = type(min_std)(0.5)
            share1 = type(min_std)(0.5)
        stats[i, 1] = wp.vector(s1[0], s1[1], s1[2], s1[3] * share1)
    stats[i, 0] = wp.vector(s0[0], s0[1], s0[2], s0[3] * share0)
    cost[i] = best
    ok[i] = one


@wp.func
def _source_adjoint(img: wp.array2d[Any], params: wp.array2d[Any], s: int, y: int, x: int, half: int, n: Any,
                    dn: Any, dirs: wp.array2d[Any], gray: wp.array2d[Any], mref: Any, rvar: Any, st: Any, g: Any):
    """Replay of :func:`_source_cost` for cotangent ``g`` of its cost: ``(d / d dn, d / d n)`` where
    ``dn = d <dp, n>`` is the ray parameters' shared numerator."""
    zero = g * type(g)(0.0)
    side = 2 * half + 1
    kk = side * side
    r0 = _row(params, s, 0)
    r1 = _row(params, s, 3)
    r2 = _row(params, s, 6)
    o = _row(params, s, 9)
    kk5, lens, distorted = _intrinsics(params, s)
    msv = st[0]
    num = st[1]
    den = st[2]
    # cost = 1 - num / den with num = mean(r sc), den = sqrt(rvar mean(sc^2) + eps), sc = sv - mean(sv):
    # d cost / d sc_k = -(r_k - num rvar sc_k / den^2) / (K den). Its window mean is 0 (sum_k sc_k = 0 and
    # sum_k r_k = 0: both are centred on their window's mean), so d cost / d sv_k is the same expression.
    a = -g / (type(g)(float(kk)) * den)
    b = num * rvar / (den * den)
    g_dn = zero
    g_n = wp.vector(zero, zero, zero)
    for k in range(kk):
        qy = y + k // side - half
        qx = x + k % side - half
        dq = dirs[qy, qx]
        t, dd, kept = _ray_param(dq, n, dn)
        rdq = wp.vector(wp.dot(r0, dq), wp.dot(r1, dq), wp.dot(r2, dq))
        p = o + t * rdq
        u, v, z, du, dv = _project(p, kk5, lens, distorted)
        val, gu, gv = _sample(img, u, v)
        r = gray[qy, qx] - mref
        g_sv = a * (r - b * (val - msv))
        g_p = (g_sv * gu) * du + (g_sv * gv) * dv
        g_t = wp.dot(g_p, rdq)
        g_dn += g_t / dd
        g_n += (-g_t * t / dd * kept) * dq
    return g_dn, g_n


@wp.kernel
def window_costs_adjoint_kernel(
    offset: int,
    depth: wp.array2d[Any],
    normal: wp.array2d[Any],
    py: wp.array[wp.int64],
    px: wp.array[wp.int64],
    gray: wp.array2d[Any],
    mean: wp.array2d[Any],
    var: wp.array2d[Any],
    dirs: wp.array2d[Any],
    img0: wp.array2d[Any],
    img1: wp.array2d[Any],
    params: wp.array2d[Any],
    sources: int,
    half: int,
    stats: wp.array2d[Any],
    g_cost: wp.array[Any],
    g_window_depth: wp.array[Any],
    g_window_normal: wp.array[Any],
):
    """``g_cost[i] d cost[i] / d depth`` and ``d / d normal`` at window ``i``'s centre pixel (``i = offset + tid``,
    one window per thread, no atomics: :func:`scatter_window_grads_kernel` adds them to the maps)."""
    i = offset + wp.tid()
    g = g_cost[i]
    zero = g * type(g)(0.0)
    g_window_depth[i] = zero
    g_window_normal[i] = wp.vector(zero, zero, zero)
    if g == zero:
        return
    y = int(py[i])
    x = int(px[i])
    n, ln, dn = _plane(depth, normal, dirs, y, x)
    mref = mean[y, x]
    rvar = var[y, x]
    g_dn = zero
    g_n = wp.vector(zero, zero, zero)
    s0 = stats[i, 0]
    if s0[3] != zero:
        a, b = _source_adjoint(img0, params, 0, y, x, half, n, dn, dirs, gray, mref, rvar, s0, g * s0[3])
        g_dn += a
        g_n += b
    if sources > 1:
        s1 = stats[i, 1]
        if s1[3] != zero:
            a, b = _source_adjoint(img1, params, 1, y, x, half, n, dn, dirs, gray, mref, rvar, s1, g * s1[3])
            g_dn += a
            g_n += b
    dp = dirs[y, x]
    d = depth[y, x]
    g_n += (g_dn * d) * dp  # dn = d <dp, n>
    # n = nr / max(|nr|, 1e-8): the projection off the normal, over the length (plain scaling when clamped)
    scale = wp.max(ln, type(ln)(1e-8))
    g_nr = g_n / scale
    if ln >= type(ln)(1e-8):
        g_nr = g_nr - n * (wp.dot(n, g_n) / scale)
    g_window_depth[i] = g_dn * wp.dot(dp, n)
    g_window_normal[i] = g_nr


@wp.kernel
def scatter_window_grads_kernel(
    py: wp.array[wp.int64],
    px: wp.array[wp.int64],
    g_window_depth: wp.array[Any],
    g_window_normal: wp.array[Any],
    g_depth: wp.array2d[Any],
    g_normal: wp.array2d[Any],
):
    """Add window ``i``'s gradients at its centre pixel (atomics: centres may repeat; one launch, never split)."""
    i = wp.tid()
    y = int(py[i])
    x = int(px[i])
    wp.atomic_add(g_depth, y, x, g_window_depth[i])
    wp.atomic_add(g_normal, y, x, g_window_normal[i])


# explicit float32 / float64 overloads, launched as such (no per-launch type inference): {scalar: (forward,
# adjoint, scatter)}
OVERLOADS = {}
for _s, _v3, _v4 in ((wp.float32, wp.vec3, wp.vec4), (wp.float64, wp.vec3d, wp.vec4d)):
    _a = wp.array2d(dtype=_s)
    _n = wp.array2d(dtype=_v3)
    _i = wp.array(dtype=wp.int64)
    OVERLOADS[_s] = (
        wp.overload(window_costs_kernel, {
            "offset": int, "depth": _a, "normal": _n, "alpha": _a, "py": _i, "px": _i, "gray": _a, "mean": _a,
            "var": _a, "dirs": _n, "length": _a, "img0": _a, "img1": _a, "params": _a, "sources": int, "half": int,
            "min_std": _s, "grazing": _s, "alpha_min": _s, "eps": _s, "cost": wp.array(dtype=_s),
            "ok": wp.array(dtype=_s), "stats": wp.array2d(dtype=_v4)}),
        wp.overload(window_costs_adjoint_kernel, {
            "offset": int, "depth": _a, "normal": _n, "py": _i, "px": _i, "gray": _a, "mean": _a, "var": _a,
            "dirs": _n, "img0": _a, "img1": _a, "params": _a, "sources": int, "half": int,
            "stats": wp.array2d(dtype=_v4), "g_cost": wp.array(dtype=_s), "g_window_depth": wp.array(dtype=_s),
            "g_window_normal": wp.array(dtype=_v3)}),
        wp.overload(scatter_window_grads_kernel, {
            "py": _i, "px": _i, "g_window_depth": wp.array(dtype=_s), "g_window_normal": wp.array(dtype=_v3),
            "g_depth": _a, "g_normal": _n}),
    )
