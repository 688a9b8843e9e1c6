# SPDX-License-Identifier: Apache-2.0
"""CPU pixel kernels of the surfel rasterizer: one thread per tile, each surfel visiting only its own pixels.

Warp's CPU launches run one thread after another, so the per-pixel kernels of :mod:`.rasterize` and
:mod:`.rasterize_backward` test every surfel of a tile's list at each of the tile's pixels, most of them
rejected (a surfel of the CPU fit covers a few pixels of an 8 x 8 tile). Here one thread walks a tile's
list once and, for each surfel, only the pixels of its pixel rectangle (``prect``, written by
:func:`~.rasterize_binning.bin_surfels_kernel` at pixel granularity from the same conservative bound as
the tile binning: no pixel outside it can pass the alpha threshold). Each pixel's running state lives in
arrays between surfels, which are the forward's outputs and saved state themselves.

Same results bit for bit as the per-pixel kernels on the CPU: every pixel sees the surfels it can hit in
the same order with the same arithmetic (:func:`~.rasterize.record_hit`), a skipped pair changes nothing,
and each surfel's gradient terms are added to the worker's buffer in the same order (tiles in launch
order, then pixels of the tile in row-major order: a surfel appears once in a tile's list).
Compiled with ``enable_backward=False``; generic over float32 / float64.
"""

from typing import Any

import warp as wp

from .rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, ndc_depth, record_hit
from .rasterize_backward import pair_adjoint
from .rasterize_records import declare_float_overloads

wp.set_module_options({"enable_backward": False})


@wp.func
def tile_box(tile: int, tile_size: int, tiles_x: int, height: int, width: int):
    """Pixel box ``[x0, x1) x [y0, y1)`` of a tile, clipped to the image."""
    x0 = (tile % tiles_x) * tile_size
    y0 = (tile // tiles_x) * tile_size
    return x0, wp.min(x0 + tile_size, width), y0, wp.min(y0 + tile_size, height)


@wp.func
def worker_tile(tid: int, worker: int, workers: int, chunk: int):
    """Tile of thread ``tid`` of worker ``worker``'s launch: its chunks are ``worker, worker + workers, ...``."""
    return ((tid // chunk) * workers + worker) * chunk + tid % chunk


@wp.kernel
def render_forward_tiles_kernel(
    worker: int,
    workers: int,
    chunk: int,
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
    ids: wp.array[wp.int32],
    prect: wp.array[wp.vec4i],
    rays: wp.array2d[Any],
    cams: wp.array[Any],
    geo: wp.array[Any],
    nrm_face: wp.array[Any],
    color: wp.array[Any],
    opacity: wp.array[Any],
    background: wp.array[Any],
    tile_size: int,
    tiles_x: int,
    rgb: wp.array2d[Any],
    alpha: wp.array2d[Any],
    depth: wp.array2d[Any],
    median: wp.array2d[Any],
    normal: wp.array2d[Any],
    distortion: wp.array2d[Any],
    t_final: wp.array2d[Any],
    sums: wp.array2d[Any],
    last: wp.array2d[wp.int32],
    median_idx: wp.array2d[wp.int32],
    done: wp.array2d[wp.int32],
    visibility: wp.array2d[wp.int32],
):
    """Front-to-back compositing of one tile (:func:`~.rasterize.render_forward_kernel`, surfel by surfel).

    While the list is walked, ``rgb`` holds the colour sum, ``t_final`` the transmittance, ``sums`` the
    depth sums, ``normal``, ``distortion``, ``median`` and ``median_idx`` their running values,
    ``last`` the end of the pixel's walk and ``done`` whether it has stopped (scratch).
    """
    cam = cams[0]
    tile = worker_tile(wp.tid(), worker, workers, chunk)
    x0, x1, y0, y1 = tile_box(tile, tile_size, tiles_x, rgb.shape[0], rgb.shape[1])
    start = tile_start[tile]
    k_end = tile_end[tile]
    f_ref = cam.fx
    zero = type(f_ref)(0.0)
    one = type(f_ref)(1.0)
    near = cam.near
    far = cam.far
    fis = cam.filter_inv_sq
    for py in range(y0, y1):
        for px in range(x0, x1):
            rgb[py, px] = wp.vector(zero, zero, zero)
            normal[py, px] = wp.vector(zero, zero, zero)
            sums[py, px] = wp.vector(zero, zero, zero)
            distortion[py, px] = zero
            median[py, px] = zero
            median_idx[py, px] = -1
            t_final[py, px] = one
            last[py, px] = start
            done[py, px] = 0
    active = (x1 - x0) * (y1 - y0)
    k = start
    while k < k_end and active > 0:
        i = ids[k]
        r = prect[i]
        bx0 = wp.max(r[0], x0)
        bx1 = wp.min(r[2], x1)
        by0 = wp.max(r[1], y0)
        by1 = wp.min(r[3], y1)
        if bx0 < bx1 and by0 < by1:
            g = geo[i]
            op = opacity[i]
            hits = int(0)
            for py in range(by0, by1):
                for px in range(bx0, bx1):
                    if done[py, px] != 0:
                        continue
                    d = rays[py, px]
                    pix = wp.vector(type(f_ref)(px) + type(f_ref)(0.5), type(f_ref)(py) + type(f_ref)(0.5))
                    rho, z, b3, u, v, t, du, dv, dn = record_hit(d, g, pix, fis)
                    if rho > g.cutoff:  # alpha < 1/255 for sure: skip the exp
                        continue
                    a = wp.min(type(f_ref)(ALPHA_MAX), op * wp.exp(type(f_ref)(-0.5) * rho))
                    if a < type(f_ref)(ALPHA_MIN) or z < near:
                        continue
                    T = t_final[py, px]
                    test_t = T * (one - a)
                    if test_t < type(f_ref)(T_MIN):
                        done[py, px] = 1
                        active -= 1
                        continue
                    hits += 1
                    w = a * T
                    rgb[py, px] = rgb[py, px] + w * color[i]
                    normal[py, px] = normal[py, px] + w * nrm_face[i]
                    s = sums[py, px]
                    dsum = s[0]
                    m1 = s[1]
                    m2s = s[2]
                    dsum = dsum + w * z
                    m, dm = ndc_depth(z, near, far)
                    distortion[py, px] = distortion[py, px] + w * (m * m * (one - T) + m2s - type(f_ref)(2.0) * m * m1)
                    m1 = m1 + w * m
                    m2s = m2s + w * m * m
                    sums[py, px] = wp.vector(dsum, m1, m2s)
                    if T > type(f_ref)(0.5):  # noqa: SIM300  T is the running transmittance
                        median[py, px] = z
                        median_idx[py, px] = k
                    t_final[py, px] = test_t
                    last[py, px] = k + 1
            if hits > 0:
                visibility[worker, i] = visibility[worker, i] + hits
        k += 1
    for py in range(y0, y1):
        for px in range(x0, x1):
            T = t_final[py, px]
            acc = one - T
            rgb[py, px] = rgb[py, px] + T * background[0]
            alpha[py, px] = acc
            if acc > zero:
                depth[py, px] = sums[py, px][0] / acc
            else:
                depth[py, px] = zero


@wp.kernel
def render_backward_tiles_kernel(
    worker: int,
    workers: int,
    chunk: int,
    tile_start: wp.array[wp.int32],
    ids: wp.array[wp.int32],
    prect: wp.array[wp.vec4i],
    rays: wp.array2d[Any],
    cams: wp.array[Any],
    geo: wp.array[Any],
    nrm_face: wp.array[Any],
    color: wp.array[Any],
    opacity: wp.array[Any],
    background: wp.array[Any],
    tile_size: int,
    tiles_x: int,
    t_final: wp.array2d[Any],
    sums: wp.array2d[Any],
    last: wp.array2d[wp.int32],
    median_idx: wp.array2d[wp.int32],
    g_rgb: wp.array2d[Any],
    g_alpha: wp.array2d[Any],
    g_depth: wp.array2d[Any],
    g_median: wp.array2d[Any],
    g_normal: wp.array2d[Any],
    g_dist: wp.array2d[Any],
    run_t: wp.array2d[Any],
    run_rg: wp.array2d[Any],
    agg: wp.array2d[Any],
    d_uax: wp.array2d[Any],
    d_vax: wp.array2d[Any],
    d_nrm: wp.array2d[Any],
    d_auv: wp.array2d[Any],
    d_nrm_face: wp.array2d[Any],
    d_m2: wp.array2d[Any],
    d_zc: wp.array2d[Any],
    d_color: wp.array2d[Any],
    d_opacity: wp.array2d[Any],
):
    """Reverse traversal of one tile (:func:`~.rasterize_backward.render_backward_kernel`, surfel by surfel).

    Scratch per pixel: ``run_t`` the transmittance, ``run_rg`` the suffix sum and ``agg`` the aggregate
    gradients ``(g_d, g_a, g_m1, g_m2)``.
    """
    cam = cams[0]
    tile = worker_tile(wp.tid(), worker, workers, chunk)
    x0, x1, y0, y1 = tile_box(tile, tile_size, tiles_x, t_final.shape[0], t_final.shape[1])
    start = tile_start[tile]
    f_ref = cam.fx
    zero = type(f_ref)(0.0)
    one = type(f_ref)(1.0)
    near = cam.near
    far = cam.far
    fis = cam.filter_inv_sq
    k_top = start
    for py in range(y0, y1):
        for px in range(x0, x1):
            T = t_final[py, px]
            acc = one - T
            s = sums[py, px]
            gdist = g_dist[py, px]
            gdepth = g_depth[py, px]
            g_d = zero
            g_a = g_alpha[py, px] + gdist * s[2]
            if acc > zero:
                g_d = gdepth / acc
                g_a = g_a - gdepth * s[0] / (acc * acc)
            g_m1 = type(f_ref)(-2.0) * gdist * s[1]
            g_m2 = gdist * acc
            agg[py, px] = wp.vector(g_d, g_a, g_m1, g_m2)
            run_t[py, px] = T
            run_rg[py, px] = T * wp.dot(g_rgb[py, px], background[0])
            k_top = wp.max(k_top, last[py, px])
    k = k_top - 1
    while k >= start:
        i = ids[k]
        r = prect[i]
        bx0 = wp.max(r[0], x0)
        bx1 = wp.min(r[2], x1)
        by0 = wp.max(r[1], y0)
        by1 = wp.min(r[3], y1)
        if bx0 < bx1 and by0 < by1:
            g = geo[i]
            op = opacity[i]
            col = color[i]
            nf = nrm_face[i]
            for py in range(by0, by1):
                for px in range(bx0, bx1):
                    if k >= last[py, px]:
                        continue
                    d = rays[py, px]
                    pix = wp.vector(type(f_ref)(px) + type(f_ref)(0.5), type(f_ref)(py) + type(f_ref)(0.5))
                    rho, z, b3, u, v, t, du, dv, dn = record_hit(d, g, pix, fis)
                    if rho > g.cutoff:
                        continue
                    G = wp.exp(type(f_ref)(-0.5) * rho)
                    raw = op * G
                    a = wp.min(type(f_ref)(ALPHA_MAX), raw)
                    if not (a >= type(f_ref)(ALPHA_MIN) and z >= near):
                        continue
                    ag = agg[py, px]
                    T, rg, c_color, c_nf, c_op, c_auv, c_uax, c_vax, c_nrm, c_m2, c_zc = pair_adjoint(
                        run_t[py, px], run_rg[py, px], a, raw, G, op, z, col, nf, g_rgb[py, px], g_normal[py, px],
                        ag[0], ag[1], ag[2], ag[3], k == median_idx[py, px], g_median[py, px], near, far, b3, u, v,
                        t, du, dv, dn, g.auv[2], d, pix, g.m2, fis)
                    run_t[py, px] = T
                    run_rg[py, px] = rg
                    d_color[worker, i] = d_color[worker, i] + c_color
                    d_nrm_face[worker, i] = d_nrm_face[worker, i] + c_nf
                    d_opacity[worker, i] = d_opacity[worker, i] + c_op
                    if b3:
                        d_auv[worker, i] = d_auv[worker, i] + c_auv
                        d_uax[worker, i] = d_uax[worker, i] + c_uax
                        d_vax[worker, i] = d_vax[worker, i] + c_vax
                        d_nrm[worker, i] = d_nrm[worker, i] + c_nrm
                    else:
                        d_m2[worker, i] = d_m2[worker, i] + c_m2
                        d_zc[worker, i] = d_zc[worker, i] + c_zc
        k -= 1


# one compile of this module with every overload (see kernels/rasterize_records.py)
for _kernel in (render_forward_tiles_kernel, render_backward_tiles_kernel):
    declare_float_overloads(_kernel)
