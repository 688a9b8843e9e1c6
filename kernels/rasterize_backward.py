# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of the Gaussian-surfel rasterizer's backward pass: the per-pixel reverse traversal
(:func:`render_backward_kernel`, explicit adjoints of :func:`~.rasterize.render_forward_kernel`) and the
sum of the per-worker gradient buffers (:func:`reduce_gradients_kernel`).

Both compile with ``enable_backward=False``; their inputs are the forward's records and saved state
(:mod:`.rasterize`, :mod:`.rasterize_records`). Generic over float32/float64 like the forward.
"""

from typing import Any

import warp as wp

from .rasterize import ALPHA_MAX, ALPHA_MIN, ndc_depth, pixel_tile_coords, splat_hit
from .rasterize_records import declare_float_overloads
from .rasterize_warp import (
    fetch_batch,
    lane_id,
    stage_batch,
    staged_opacity,
    staged_record,
    staging_slab,
    warp_add_grads,
    warp_any,
    warp_bcast,
    warp_max,
)

# Register cap of the CUDA backward pixel kernel: uncapped, nvcc gives its float32 version 167 registers,
# one block of 256 threads per SM; at 128 two blocks fit and the kernel ran 1.24x faster (H100, 800x800,
# 100k and 1M surfels: 5.87 -> 4.70 ms, 11.26 -> 9.08 ms; 96: 5.16 / 10.06, 80: 5.02 / 10.04, 64: 8.80 /
# 18.86); the forward's cap is rasterize.FWD_MAX_REGS. Written with flat branches, the float32
# kernel fits 128 without spilling.
BWD_MAX_REGS = 128


@wp.func
def pair_adjoint(T: Any, rg: Any, a: Any, raw: Any, G: Any, op: Any, z: Any, col: Any, nf: Any, gc: Any, gn: Any,
                 g_d: Any, g_a: Any, g_m1: Any, g_m2: Any, median: bool, gmed: Any, near: Any, far: Any, b3: bool,
                 u: Any, v: Any, t: Any, du: Any, dv: Any, dn: Any, a_n: Any, d: Any, pix: Any, m2: Any, fis: Any):
    """The adjoint of one (pixel, surfel) pair that contributed, walking back: both pixel backward kernels' terms.

    ``T`` and ``rg`` are the pixel's transmittance after the surfel and suffix sum; ``a``, ``raw``, ``G``, ``op``,
    ``z`` and ``b3, u, v, t, du, dv, dn`` the pair's alpha, unclamped alpha, Gaussian, opacity, depth and
    :func:`~.rasterize.splat_hit` terms; ``col``, ``nf`` the surfel's colour and facing normal; ``gc``, ``gn`` and
    ``g_d, g_a, g_m1, g_m2`` the pixel's upstream and aggregate gradients; ``median`` whether the surfel is the
    pixel's median (``gmed`` its gradient); ``a_n`` the record's ``a.n``, ``m2`` its centre in pixels.

    Returns ``(T_i, rg, c_color, c_nf, c_op, c_auv, c_uax, c_vax, c_nrm, c_m2, c_zc)``: the transmittance before the
    surfel, the suffix sum with it, and its gradient terms (the 3D branch's or the filter's, the other zero).
    """
    one = type(T)(1.0)
    zero = type(T)(0.0)
    Ti = T / (one - a)
    w = a * Ti
    m, dm = ndc_depth(z, near, far)
    gf = wp.dot(gc, col) + g_d * z + wp.dot(gn, nf) + g_a + g_m1 * m + g_m2 * m * m
    g_alpha_i = Ti * gf - rg / (one - a)
    gz = w * (g_d + (g_m1 + type(T)(2.0) * m * g_m2) * dm)
    if median:
        gz = gz + gmed
    g_raw = wp.where(raw < type(T)(ALPHA_MAX), g_alpha_i, zero)
    g_rho = type(T)(-0.5) * G * op * g_raw
    z3 = wp.vector(zero, zero, zero)
    c_auv = z3
    c_uax = z3
    c_vax = z3
    c_nrm = z3
    c_m2 = wp.vector(zero, zero)
    c_zc = zero
    if b3:
        gu = type(T)(2.0) * u * g_rho
        gv = type(T)(2.0) * v * g_rho
        gt = gz + gu * du + gv * dv
        inv_dn = one / dn
        gdn = gt * a_n * inv_dn * inv_dn
        c_auv = wp.vector(gu, gv, -gt * inv_dn)
        c_uax = (gu * t) * d
        c_vax = (gv * t) * d
        c_nrm = gdn * d
    else:
        c_m2 = (type(T)(-2.0) * fis * g_rho) * (pix - m2)
        c_zc = gz
    return Ti, rg + w * gf, w * gc, w * gn, g_raw * G, c_auv, c_uax, c_vax, c_nrm, c_m2, c_zc


@wp.kernel(enable_backward=False, cuda_max_registers=BWD_MAX_REGS)
def render_backward_kernel(
    offset: int,
    worker: int,
    tile_start: wp.array[wp.int32],
    ids: wp.array[wp.int32],
    rays: wp.array2d[Any],
    cams: wp.array[Any],
    geo4: wp.array2d[Any],
    nrm_face: wp.array[Any],
    color: wp.array[Any],
    opacity: wp.array[Any],
    background: wp.array[Any],
    tile_size: int,
    tiles_x: int,
    coop: int,
    batch: int,
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
    """Reverse traversal of one pixel: per-surfel gradients into this worker's buffers.

    Every output is a sum over contributions of ``w_i f_i`` (colour, depth, normal, 1, m, m^2)
    plus ``T_end * background``; the suffix sum ``rg = sum_{j>i} w_j (g . f_j) + T_end g . bg``
    gives ``dL/dalpha_i = T_i (g . f_i) - rg / (1 - alpha_i)`` with ``T_i`` recovered from the
    saved final transmittance. Distortion ``= A M2 - M1^2`` (equal to the forward's pairwise sum)
    and depth ``= D / A`` are differentiated through their aggregates.

    With ``coop`` (CUDA) the 32 pixels of a warp walk their tile's list together, from the warp's
    largest ``last`` down, each pixel contributing only below its own, and a surfel's 22 gradient values are
    summed over the warp, then added with one atomic per value (:func:`warp_add_grads`); without it (CPU) each pixel
    walks from its own ``last`` and adds its own terms. Same per-pixel arithmetic either way.
    """
    cam = cams[0]
    tile, px, py = pixel_tile_coords(wp.tid() + offset, tile_size, tiles_x)
    # pixels past the image edge (partial tiles) still walk with their warp, contributing nothing
    inside = px < t_final.shape[1] and py < t_final.shape[0]
    px = wp.min(px, t_final.shape[1] - 1)
    py = wp.min(py, t_final.shape[0] - 1)
    start = tile_start[tile]
    end = start
    if inside:
        end = last[py, px]
    d = rays[py, px]
    f_ref = d[0]
    zero = type(f_ref)(0.0)
    one = type(f_ref)(1.0)
    near = cam.near
    far = cam.far
    fis = cam.filter_inv_sq
    pix = wp.vector(type(f_ref)(px) + type(f_ref)(0.5), type(f_ref)(py) + type(f_ref)(0.5))
    T = t_final[py, px]
    acc = one - T
    s = sums[py, px]
    gc = g_rgb[py, px]
    gn = g_normal[py, px]
    gdist = g_dist[py, px]
    gdepth = g_depth[py, px]
    gmed = g_median[py, px]
    med_k = median_idx[py, px]
    # aggregate gradients: A = sum w, D = sum w z, M1 = sum w m, M2 = sum w m^2
    g_d = zero
    g_a = g_alpha[py, px] + gdist * s[2]
    if acc > zero:
        g_d = gdepth / acc
        g_a = g_a - gdepth * s[0] / (acc * acc)
    g_m1 = type(f_ref)(-2.0) * gdist * s[1]
    g_m2 = gdist * acc
    rg = T * wp.dot(gc, background[0])
    z3 = wp.vector(zero, zero, zero)
    z2 = wp.vector(zero, zero)
    lane = lane_id(coop)
    slab = staging_slab(f_ref)
    kb = warp_max(end, coop) - 1
    while kb >= start:
        nb = wp.min(batch, kb - start + 1)
        mine = fetch_batch(ids, kb, -1, nb, lane, color, nrm_face)
        stage_batch(slab, geo4, opacity, mine, lane, nb, coop)
        for j in range(nb):
            k = kb - j
            i = warp_bcast(mine, j, coop)
            U, V, n, auv, m2, zc, cut = staged_record(slab, geo4, i, j, coop)
            # the pair's test, then its terms, one level of branches each: Warp turns an assignment under nested
            # ifs into a select per level for every value the loop carries (see the forward kernel)
            rho, z, b3, u, v, t, du, dv, dn = splat_hit(d, U, V, n, auv, m2, zc, cut, pix, fis)
            hit = False
            op = zero
            G = zero
            raw = zero
            a = zero
            if k < end and not (rho > cut):
                op = staged_opacity(slab, geo4, opacity, i, j, coop)
                G = wp.exp(type(f_ref)(-0.5) * rho)
                raw = op * G
                a = wp.min(type(f_ref)(ALPHA_MAX), raw)
                hit = a >= type(f_ref)(ALPHA_MIN) and z >= near
            c_color = z3
            c_nf = z3
            c_op = zero
            c_auv = z3
            c_uax = z3
            c_vax = z3
            c_nrm = z3
            c_m2 = z2
            c_zc = zero
            if hit:
                T, rg, c_color, c_nf, c_op, c_auv, c_uax, c_vax, c_nrm, c_m2, c_zc = pair_adjoint(
                    T, rg, a, raw, G, op, z, color[i], nrm_face[i], gc, gn, g_d, g_a, g_m1, g_m2, k == med_k, gmed,
                    near, far, b3, u, v, t, du, dv, dn, auv[2], d, pix, m2, fis)
            # warp-uniform from here: every lane of the warp takes the same branches
            if warp_any(hit, coop):
                warp_add_grads(worker, i, c_color, c_nf, c_op, c_auv, c_uax, c_vax, c_nrm, c_m2, c_zc, d_color,
                               d_nrm_face, d_opacity, d_auv, d_uax, d_vax, d_nrm, d_m2, d_zc, hit, b3, coop)
        kb = kb - nb


@wp.kernel(enable_backward=False)
def reduce_gradients_kernel(
    offset: int,
    d_uax: wp.array2d[Any],
    d_vax: wp.array2d[Any],
    d_nrm: wp.array2d[Any],
    d_auv: wp.array2d[Any],
    d_nrm_face: wp.array2d[Any],
    d_m2: wp.array2d[Any],
    d_zc: wp.array2d[Any],
    d_color: wp.array2d[Any],
    d_opacity: wp.array2d[Any],
    g_uax: wp.array[Any],
    g_vax: wp.array[Any],
    g_nrm: wp.array[Any],
    g_auv: wp.array[Any],
    g_nrm_face: wp.array[Any],
    g_m2: wp.array[Any],
    g_zc: wp.array[Any],
    g_color: wp.array[Any],
    g_opacity: wp.array[Any],
):
    """Sum the per-worker gradient buffers of one surfel into the tape's gradient arrays."""
    i = wp.tid() + offset
    for w in range(d_uax.shape[0]):
        g_uax[i] = g_uax[i] + d_uax[w, i]
        g_vax[i] = g_vax[i] + d_vax[w, i]
        g_nrm[i] = g_nrm[i] + d_nrm[w, i]
        g_auv[i] = g_auv[i] + d_auv[w, i]
        g_nrm_face[i] = g_nrm_face[i] + d_nrm_face[w, i]
        g_m2[i] = g_m2[i] + d_m2[w, i]
        g_zc[i] = g_zc[i] + d_zc[w, i]
        g_color[i] = g_color[i] + d_color[w, i]
        if g_opacity.shape[0] > 0:
            g_opacity[i] = g_opacity[i] + d_opacity[w, i]


@wp.kernel(enable_backward=False)
def shift_gradient_kernel(
    offset: int,
    cams: wp.array[Any],
    uax: wp.array[Any],
    vax: wp.array[Any],
    nrm: wp.array[Any],
    g_uax: wp.array[Any],
    g_vax: wp.array[Any],
    g_nrm: wp.array[Any],
    g_m2: wp.array[Any],
    g_shift: wp.array[Any],
):
    """Add ``dL/dshift`` of each surfel from the pixel kernels' sums (run after them, before the preparation's
    adjoint adds to ``g_m2``).

    A shift moves the filter branch's centre (``pixel - (m2 + shift)``: the pixel kernels' ``g_m2`` is already its
    gradient) and the object-space branch's rays (``d' = d - R^T [Kinv2 shift, 0]``, so
    ``dL/dshift = -Kinv2^T (R gd)[:2]`` with ``gd = sum over pixels of dL/dd``). Per pixel
    ``dL/dd = (gu t) U + (gv t) V + gdn n``, whose pixel factors the kernels already summed times ``d`` into
    ``g_uax``, ``g_vax`` and ``g_nrm``; a ray's camera-z is 1 (``Camera.pixel_rays``), so the third row of ``R``
    recovers each factor's sum: ``sum(gu t) = R[2] . g_uax``. One pass per surfel instead of a 2-vector per pixel.
    """
    i = wp.tid() + offset
    cam = cams[0]
    R = cam.R
    r2 = wp.vector(R[2, 0], R[2, 1], R[2, 2])
    gd = wp.dot(r2, g_uax[i]) * uax[i] + wp.dot(r2, g_vax[i]) * vax[i] + wp.dot(r2, g_nrm[i]) * nrm[i]
    gcx = R[0, 0] * gd[0] + R[0, 1] * gd[1] + R[0, 2] * gd[2]
    gcy = R[1, 0] * gd[0] + R[1, 1] * gd[1] + R[1, 2] * gd[2]
    fx = cam.fx
    fy = cam.fy
    g_shift[i] = g_shift[i] + g_m2[i] + wp.vector(-gcx / fx, gcx * cam.skew / (fx * fy) - gcy / fy)


# one compile of this module with every overload (see kernels/rasterize_records.py)
for _kernel in (render_backward_kernel, reduce_gradients_kernel, shift_gradient_kernel):
    declare_float_overloads(_kernel)
