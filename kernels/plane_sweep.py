# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of the plane sweep's score: every hypothesis plane's window NCC against every source view.

Three launches per chunk of planes, each writing disjoint outputs (so a CPU launch may be split across threads;
the first parameter is the thread offset, the second ``strip``: how many consecutive pixels a thread takes, 1 on
CUDA, more on the CPU where a thread's set-up is a good part of a pixel's time):

* :func:`warp_sources_kernel`, per (plane, reference row, strip of columns): each pixel's depth on the plane (a
  plane facing the reference camera at inverse depth ``planes[p]``; or a level plane at height ``planes[p]``,
  where the ray meets it at ``(h - a) / b`` with ``a`` the camera's height and ``b`` the height the ray gains
  per unit depth, -1 outside ``[lo, hi]``), the point ``o_s + depth R_s d`` in each source's frame, projected
  with the source's pinhole and OpenCV distortion (``multiview_ncc``'s projection) and sampled bilinearly from
  its grey image as ``grid_sample(mode="bilinear", padding_mode="zeros", align_corners=False)`` does. Writes
  the samples and, per plane and pixel, a bit per source that says whether the centre counts (positive z and
  depth, inside the source's image).
* :func:`window_rows_kernel`, per (plane, source, row, strip of columns): sums over each window's row (clipped
  to the image) of the sample ``s``, ``s^2`` and ``s r`` (``r``: the reference's grey level).
* :func:`window_costs_kernel`, per (plane, strip of rows, column): the window's sums over its rows, the NCC
  ``cov / sqrt(var_s var_r + 1e-12)`` per source (moments over the window's in-image pixels, -1 where the centre
  does not count or the source window is untextured), and the mean of the best ``best`` of them.

A strip's sums start at its first pixel and slide along it, accumulated in float64: the variance of a nearly flat
window (``E[s^2] - E[s]^2``) would otherwise carry a float32 sliding sum's round-off into the NCC; one pixel a
thread (CUDA) sums directly in float32. The NCC itself is formed in float32 from the sums (so it may pass +-1 by
round-off). Nothing here is differentiated.
"""

import warp as wp

from .multiview_ncc import _intrinsics, _project_value, _row

wp.set_module_options({"enable_backward": False})

FRONTO = 0
"""``family``: planes facing the reference camera, ``planes`` holds their inverse depths."""
LEVEL = 1
"""``family``: level planes, ``planes`` holds their heights along the capture's up direction."""
MAX_SOURCES = 8
"""Sources per reference view at most (the sweep uses 4; each takes a bit of the validity mask and a slot of
the windows' per-source sums)."""
_sources_vec = wp.types.vector(length=MAX_SOURCES, dtype=wp.float32)
_sums_vec = wp.types.vector(length=MAX_SOURCES, dtype=wp.float64)


@wp.func
def _tap(img: wp.array3d(dtype=wp.float32), k: int, y: int, x: int):
    """Source ``k``'s grey level at pixel ``(y, x)``, 0 outside the image."""
    if y >= 0 and y < img.shape[1] and x >= 0 and x < img.shape[2]:
        return img[k, y, x]
    return 0.0


@wp.func
def _sample_zeros(img: wp.array3d(dtype=wp.float32), k: int, u: float, v: float):
    """Bilinear grey level of source ``k`` at pixel coordinates ``(u, v)`` (centres at +0.5), taps outside the
    image reading 0 (``grid_sample``'s zero padding)."""
    ix = u - 0.5
    iy = v - 0.5
    # beyond a pixel outside the image every tap is outside (this also keeps the float -> int conversion in range;
    # NaN fails the tests)
    if not (ix > -1.0 and ix < float(img.shape[2]) and iy > -1.0 and iy < float(img.shape[1])):
        return 0.0
    x0 = int(wp.floor(ix))
    y0 = int(wp.floor(iy))
    e = ix - float(x0)
    f = iy - float(y0)
    top = _tap(img, k, y0, x0) * (1.0 - e) + _tap(img, k, y0, x0 + 1) * e
    bottom = _tap(img, k, y0 + 1, x0) * (1.0 - e) + _tap(img, k, y0 + 1, x0 + 1) * e
    return top * (1.0 - f) + bottom * f


@wp.func
def _plane_depth(family: int, plane: float, a: float, b: float, lo: float, hi: float):
    """Depth along the reference ray of a pixel on one plane (see the module docstring)."""
    if family == FRONTO:
        return 1.0 / plane
    bb = b
    if wp.abs(bb) < 1.0e-6:
        bb = 1.0e-6
    d = (plane - a) / bb
    if d >= lo and d <= hi:
        return d
    return -1.0


@wp.kernel
def warp_sources_kernel(offset: int, strip: int, planes: wp.array(dtype=wp.float32), family: int,
                        height: wp.array2d(dtype=wp.float32), rate: wp.array2d(dtype=wp.float32), lo: float,
                        hi: float, dirs: wp.array2d(dtype=wp.vec3), images: wp.array3d(dtype=wp.float32),
                        params: wp.array2d(dtype=wp.float32),
                        warped: wp.array4d(dtype=wp.float32), valid: wp.array3d(dtype=wp.int32)):
    """Thread ``offset + tid`` = ``(p, y, strip of x)`` of ``valid`` [P, H, W]: ``warped[p, :, y, x]`` [P, K, H, W]
    and the validity bits ``valid[p, y, x]``. ``params``: one ``multiview_ncc`` source row per source [K, 23]."""
    i = offset + wp.tid()
    H = valid.shape[1]
    W = valid.shape[2]
    n = (W + strip - 1) // strip
    p = i // (H * n)
    y = (i // n) % H
    x0 = (i % n) * strip
    x1 = wp.min(x0 + strip, W)
    plane = planes[p]
    fw = float(images.shape[2])
    fh = float(images.shape[1])
    for k in range(images.shape[0]):
        r0 = _row(params, k, 0)
        r1 = _row(params, k, 3)
        r2 = _row(params, k, 6)
        o = _row(params, k, 9)
        kk, lens, distorted = _intrinsics(params, k)
        for x in range(x0, x1):
            d = _plane_depth(family, plane, height[y, x], rate[y, x], lo, hi)
            ray = dirs[y, x]
            pt = o + d * wp.vec3(wp.dot(r0, ray), wp.dot(r1, ray), wp.dot(r2, ray))
            u, v = _project_value(pt, kk, lens, distorted)
            warped[p, k, y, x] = _sample_zeros(images, k, u, v)
            bits = int(0)
            if k > 0:
                bits = valid[p, y, x]
            if pt[2] > 0.0 and d > 0.0 and u >= 0.0 and u <= fw and v >= 0.0 and v <= fh:
                bits = bits | (1 << k)
            valid[p, y, x] = bits


@wp.func
def _moments(s: float, r: float):
    """``(s, s^2, s r)`` in float64 (a sliding sum keeps its round-off far under the variance's cancellation)."""
    sd = wp.float64(s)
    return wp.vec3d(sd, sd * sd, sd * wp.float64(r))


@wp.kernel
def window_rows_kernel(offset: int, strip: int, warped: wp.array4d(dtype=wp.float32),
                       gray: wp.array2d(dtype=wp.float32), half: int, rows: wp.array4d(dtype=wp.vec3)):
    """Thread ``offset + tid`` = ``(p, k, y, strip of x)`` of ``rows`` [P, K, H, W]: ``(sum s, sum s^2, sum s r)``
    over the in-image pixels ``(y, x - half .. x + half)``: with one pixel a thread a float32 sum; else summed at
    the strip's first pixel and slid from there (a pixel enters and one leaves per step) in float64."""
    i = offset + wp.tid()
    K = rows.shape[1]
    H = rows.shape[2]
    W = rows.shape[3]
    n = (W + strip - 1) // strip
    x0 = (i % n) * strip
    y = (i // n) % H
    k = (i // (n * H)) % K
    p = i // (n * H * K)
    if strip == 1:  # CUDA: one pixel a thread, a direct float32 sum (float64 is slow on most GPUs)
        acc32 = wp.vec3(0.0)
        for xx in range(wp.max(x0 - half, 0), wp.min(x0 + half + 1, W)):
            s = warped[p, k, y, xx]
            acc32 += wp.vec3(s, s * s, s * gray[y, xx])
        rows[p, k, y, x0] = acc32
        return
    acc = wp.vec3d(0.0)
    for xx in range(wp.max(x0 - half, 0), wp.min(x0 + half + 1, W)):
        acc += _moments(warped[p, k, y, xx], gray[y, xx])
    rows[p, k, y, x0] = wp.vec3(acc)
    for x in range(x0 + 1, wp.min(x0 + strip, W)):
        xin = x + half
        if xin < W:
            acc += _moments(warped[p, k, y, xin], gray[y, xin])
        xout = x - half - 1
        if xout >= 0:
            acc -= _moments(warped[p, k, y, xout], gray[y, xout])
        rows[p, k, y, x] = wp.vec3(acc)


@wp.func
def _ncc(acc: wp.vec3, n: float, mr: float, vr: float, counts: int, min_texture: float):
    """A source window's NCC from its sums ``acc`` over ``n`` pixels (-1 where it does not count or is untextured)."""
    ms = acc[0] / n
    vs = wp.max(acc[1] / n - ms * ms, 0.0)
    c = -1.0
    if counts != 0 and vs > min_texture:
        c = (acc[2] / n - ms * mr) / wp.sqrt(vs * vr + 1.0e-12)
    return c


@wp.func
def _best_mean(nccs: _sources_vec, K: int, best: int):
    """The mean of the ``best`` largest of ``nccs[:K]``."""
    total = float(0.0)
    taken = int(0)
    for _j in range(best):
        top = int(-1)
        for k in range(K):
            if (taken >> k) & 1 == 0:
                if top < 0:  # noqa: SIM114 - Warp evaluates both sides of `or`: nccs[-1] would be read
                    top = k
                elif nccs[k] > nccs[top]:
                    top = k
        taken = taken | (1 << top)
        total += nccs[top]
    return total / float(best)


@wp.kernel
def window_costs_kernel(offset: int, strip: int, rows: wp.array4d(dtype=wp.vec3), valid: wp.array3d(dtype=wp.int32),
                        mean: wp.array2d(dtype=wp.float32), var: wp.array2d(dtype=wp.float32), half: int, best: int,
                        min_texture: float, cost: wp.array3d(dtype=wp.float32)):
    """Thread ``offset + tid`` = ``(p, strip of y, x)`` of ``cost`` [P, H, W]: the mean of the ``best`` largest
    source NCCs of the window centred at ``(y, x)`` (``mean``, ``var``: the reference window's moments). With one
    row a thread each source's column sum of ``rows`` is a float32 sum; else it starts at the strip's first row and
    slides down it in float64."""
    i = offset + wp.tid()
    K = rows.shape[1]
    H = cost.shape[1]
    W = cost.shape[2]
    n = (H + strip - 1) // strip
    x = i % W
    y0 = ((i // W) % n) * strip
    p = i // (W * n)
    cols = float(wp.min(x + half + 1, W) - wp.max(x - half, 0))
    s0 = _sums_vec()
    s1 = _sums_vec()
    s2 = _sums_vec()
    nccs = _sources_vec()
    for y in range(y0, wp.min(y0 + strip, H)):
        bits = valid[p, y, x]
        count = cols * float(wp.min(y + half + 1, H) - wp.max(y - half, 0))
        mr = mean[y, x]
        vr = var[y, x]
        for k in range(K):
            if strip == 1:  # CUDA: one row a thread, a direct float32 sum (float64 is slow on most GPUs)
                acc32 = wp.vec3(0.0)
                for yy in range(wp.max(y - half, 0), wp.min(y + half + 1, H)):
                    acc32 += rows[p, k, yy, x]
                nccs[k] = _ncc(acc32, count, mr, vr, (bits >> k) & 1, min_texture)
                continue
            acc = wp.vec3d(s0[k], s1[k], s2[k])
            if y == y0:
                acc = wp.vec3d(0.0)
                for yy in range(wp.max(y0 - half, 0), wp.min(y0 + half + 1, H)):
                    acc += wp.vec3d(rows[p, k, yy, x])
            else:
                if y + half < H:
                    acc += wp.vec3d(rows[p, k, y + half, x])
                if y - half - 1 >= 0:
                    acc -= wp.vec3d(rows[p, k, y - half - 1, x])
            s0[k] = acc[0]
            s1[k] = acc[1]
            s2[k] = acc[2]
            nccs[k] = _ncc(wp.vec3(acc), count, mr, vr, (bits >> k) & 1, min_texture)
        cost[p, y, x] = _best_mean(nccs, K, best)
