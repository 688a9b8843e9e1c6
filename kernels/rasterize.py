# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of the Gaussian-surfel rasterizer (2D Gaussian splatting, ray-splat intersection).

Kernels are generic over float32/float64 (``typing.Any`` arguments). The per-surfel
:func:`prepare_surfels_kernel` is differentiated by Warp's autodiff (straight-line code; a render that nothing
differentiates runs :func:`prepare_records_kernel`, the same arithmetic with the packing fused in); the
per-pixel compositing kernels have explicit adjoints (:func:`~.rasterize_backward.render_backward_kernel`
in :mod:`.rasterize_backward`, reverse traversal with the saved final transmittance) and compile with
``enable_backward=False``.

Kernel arguments are records (``@wp.struct``, one type per float dtype, see
:func:`~.rasterize_records.float_structs`): ``cams`` a one-element array of
:class:`~.rasterize_records.CameraRecord` in device memory (everything the kernels read per view) and ``geo``
an array of :class:`~.rasterize_records.SurfelRecord` (what the pixel kernels test per surfel, written by
:func:`pack_surfels_kernel`; the per-pixel kernels read it as ``geo4``, four 4-vectors a record, see
:func:`~.rasterize_warp.staged_record`). Both are inputs only: nothing is differentiated w.r.t. the camera. The records
and the float32 / float64 overload declarations are in :mod:`.rasterize_records`.

Per-surfel quantities the pixel kernels read (written by :func:`prepare_surfels_kernel`):
``uax = t_u / s_u`` and ``vax = t_v / s_v`` (tangent axes divided by the scales, so the local
coordinates of a world offset ``x`` are ``(dot(x, uax), dot(x, vax))``), ``nrm`` the plane normal
(local +z), ``nrm_face`` the normal flipped to face the camera, ``m2`` the projected centre in
pixels (lens distortion applied), ``zc`` the centre's z-depth and ``color`` the evaluated colour.
"""

from typing import Any

import warp as wp

from .rasterize_records import CAMERA as CAMERA
from .rasterize_records import SURFEL as SURFEL
from .rasterize_records import CameraRecord as CameraRecord
from .rasterize_records import SurfelRecord as SurfelRecord
from .rasterize_records import declare_float_overloads
from .rasterize_records import float_structs as float_structs
from .rasterize_warp import (
    fetch_batch,
    lane_id,
    stage_batch,
    staged_opacity,
    staged_record,
    staging_slab,
    warp_any,
    warp_bcast,
    warp_count,
)
from .rotation import quat_axes

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (3DGS/2DGS convention)
ALPHA_MAX = 0.99  # alpha clamp: keeps 1 / (1 - alpha) <= 100 in the reverse traversal (2DGS)
T_MIN = 1.0e-4  # early stop once the transmittance would fall below this (2DGS)
SCALE_MIN = 1.0e-30  # scales are clamped here so 1 / s stays finite in float32
PARALLEL_EPS = 1.0e-12  # |dot(ray, normal)| below this: the ray is parallel to the surfel plane
RHO_BIG = 1.0e30  # rho3d of a parallel ray or an overflowing intersection: the filter branch wins
QUAT_MIN_SQ = 1.0e-30  # |q|^2 below this: identity rotation (documented fallback, zero gradient)
# rho3d <= rho2d + RHO_TIE picks the object-space branch. At the ray through the centre both exponents
# are 0 in exact arithmetic and only rounding (which differs between CPU and CUDA: nvcc fuses
# a + t * b into an FMA) decided the branch, hence the gradient (the branches' derivatives differ at
# the tie). Rounding leaves rho3d ~ (|a.U| eps)^2 there: ~1e-13 in float32 for |a.U| ~ 10; the
# slack changes alpha by at most a relative 5e-10.
RHO_TIE = 1.0e-9
# Register cap of the CUDA forward pixel kernel: ptxas gives its float32 version 83 registers (2 blocks of 256
# threads an SM); at 80 three fit, with 8 bytes of spill, and the kernel ran 1.19-1.25x faster (H100, 800x800,
# beside gsplat in one process: 1.125 -> 0.920 ms at 100k surfels, 2.275 -> 1.821 ms at 1M; benchmarks/gpu.md).
FWD_MAX_REGS = 80

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199


@wp.func
def cam_rotate(cam: Any, v: Any):
    """World-to-camera rotation applied to ``v``."""
    R = cam.R
    return wp.vector(
        R[0, 0] * v[0] + R[0, 1] * v[1] + R[0, 2] * v[2],
        R[1, 0] * v[0] + R[1, 1] * v[1] + R[1, 2] * v[2],
        R[2, 0] * v[0] + R[2, 1] * v[1] + R[2, 2] * v[2],
    )


@wp.func
def cam_point(cam: Any, p: Any):
    """World point ``p`` in camera coordinates."""
    r = cam_rotate(cam, p)
    return wp.vector(r[0] + cam.t[0], r[1] + cam.t[1], r[2] + cam.t[2])


@wp.func
def project_pixel(cam: Any, pc: Any):
    """Pixel coordinates of a camera-frame point with ``pc.z > 0`` (OpenCV distortion applied)."""
    one = type(pc[0])(1.0)
    two = type(pc[0])(2.0)
    x = pc[0] / pc[2]
    y = pc[1] / pc[2]
    r2 = x * x + y * y
    radial = one + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3))
    xd = x * radial + two * cam.p1 * x * y + cam.p2 * (r2 + two * x * x)
    yd = y * radial + cam.p1 * (r2 + two * y * y) + two * cam.p2 * x * y
    return wp.vector(cam.fx * xd + cam.skew * yd + cam.cx, cam.fy * yd + cam.cy)


@wp.func
def sh_color(sh: wp.array2d[Any], i: int, degree: int, d: Any):
    """3DGS real spherical harmonics of ``degree`` (0..3) in unit direction ``d``, plus 0.5."""
    x = d[0]
    y = d[1]
    z = d[2]
    c = sh[i, 0] * type(x)(SH_C0)
    if degree > 0:
        c = c - sh[i, 1] * (type(x)(SH_C1) * y) + sh[i, 2] * (type(x)(SH_C1) * z) - sh[i, 3] * (type(x)(SH_C1) * x)
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            c = c + sh[i, 4] * (type(x)(1.0925484305920792) * x * y)
            c = c + sh[i, 5] * (type(x)(-1.0925484305920792) * y * z)
            c = c + sh[i, 6] * (type(x)(0.31539156525252005) * (type(x)(2.0) * zz - xx - yy))
            c = c + sh[i, 7] * (type(x)(-1.0925484305920792) * x * z)
            c = c + sh[i, 8] * (type(x)(0.5462742152960396) * (xx - yy))
            if degree > 2:
                c = c + sh[i, 9] * (type(x)(-0.5900435899266435) * y * (type(x)(3.0) * xx - yy))
                c = c + sh[i, 10] * (type(x)(2.890611442640554) * x * y * z)
                c = c + sh[i, 11] * (type(x)(-0.4570457994644658) * y * (type(x)(4.0) * zz - xx - yy))
                c = c + sh[i, 12] * (
                    type(x)(0.3731763325901154) * z * (type(x)(2.0) * zz - type(x)(3.0) * xx - type(x)(3.0) * yy)
                )
                c = c + sh[i, 13] * (type(x)(-0.4570457994644658) * x * (type(x)(4.0) * zz - xx - yy))
                c = c + sh[i, 14] * (type(x)(1.445305721320277) * z * (xx - yy))
                c = c + sh[i, 15] * (type(x)(-0.5900435899266435) * x * (xx - type(x)(3.0) * yy))
    half = type(x)(0.5)
    zero = type(x)(0.0)
    return wp.vector(wp.max(c[0] + half, zero), wp.max(c[1] + half, zero), wp.max(c[2] + half, zero))


@wp.func
def surfel_frame(p: Any, q: Any, s: Any, cam: Any):
    """A surfel's ``(uax, vax, nrm, auv, nrm_face, m2, zc)`` from its centre, rotation and scales (module
    docstring); ``m2`` is 0 for a centre at or behind the near plane (culled there, never read)."""
    f_ref = p[0]
    tu, tv, n = quat_axes(q, QUAT_MIN_SQ)
    su = wp.max(s[0], type(f_ref)(SCALE_MIN))
    sv = wp.max(s[1], type(f_ref)(SCALE_MIN))
    U = tu / su
    V = tv / sv
    view = p - cam.center
    auv = wp.vector(-wp.dot(view, U), -wp.dot(view, V), -wp.dot(view, n))
    # facing the camera: dot(normal, centre - camera) < 0
    facing = n
    if wp.dot(n, view) > type(f_ref)(0.0):
        facing = -n
    pc = cam_point(cam, p)
    m2 = wp.vector(type(f_ref)(0.0), type(f_ref)(0.0))
    if pc[2] > cam.near:
        m2 = project_pixel(cam, pc)
    return U, V, n, auv, facing, m2, pc[2]


@wp.func
def surfel_color(sh: wp.array2d[Any], i: int, sh_degree: int, view: Any):
    """Surfel ``i``'s colour seen along ``view`` (centre - camera): its SH of ``sh_degree`` (:func:`sh_color`), or
    ``sh[i, 0]`` as it is for ``sh_degree < 0`` (plain RGB)."""
    c = sh[i, 0]
    if sh_degree >= 0:
        vl2 = wp.dot(view, view)
        d = wp.vector(type(vl2)(0.0), type(vl2)(0.0), type(vl2)(1.0))
        if vl2 > type(vl2)(1.0e-30):
            d = view / wp.sqrt(vl2)
        c = sh_color(sh, i, sh_degree, d)
    return c


@wp.kernel
def prepare_surfels_kernel(
    offset: int,
    means: wp.array[Any],
    quats: wp.array[Any],
    scales: wp.array[Any],
    sh: wp.array2d[Any],
    cams: wp.array[Any],
    sh_degree: int,
    uax: wp.array[Any],
    vax: wp.array[Any],
    nrm: wp.array[Any],
    auv: wp.array[Any],
    nrm_face: wp.array[Any],
    m2: wp.array[Any],
    zc: wp.array[Any],
    color: wp.array[Any],
):
    """Per-surfel frame, projected centre, depth and colour (differentiated by Warp autodiff)."""
    cam = cams[0]
    i = wp.tid() + offset
    p = means[i]
    U, V, n, a, facing, c2, z = surfel_frame(p, quats[i], scales[i], cam)
    uax[i] = U
    vax[i] = V
    nrm[i] = n
    auv[i] = a
    nrm_face[i] = facing
    m2[i] = c2
    zc[i] = z
    color[i] = surfel_color(sh, i, sh_degree, p - cam.center)


@wp.kernel(enable_backward=False)
def prepare_records_kernel(
    offset: int,
    means: wp.array[Any],
    quats: wp.array[Any],
    scales: wp.array[Any],
    sh: wp.array2d[Any],
    cams: wp.array[Any],
    sh_degree: int,
    cutoff: wp.array[Any],
    geo4: wp.array2d[Any],
    nrm_face: wp.array[Any],
    color: wp.array[Any],
):
    """:func:`prepare_surfels_kernel` then :func:`pack_surfels_kernel` in one pass, for a forward that nothing
    differentiates: each record written as its four quads (the layout :func:`~.rasterize_warp.staged_record`
    reads), with the facing normal and the colour; the intermediate per-surfel arrays are never written."""
    cam = cams[0]
    i = wp.tid() + offset
    p = means[i]
    U, V, n, a, facing, c2, z = surfel_frame(p, quats[i], scales[i], cam)
    geo4[i, 0] = wp.vector(U[0], U[1], U[2], V[0])
    geo4[i, 1] = wp.vector(V[1], V[2], n[0], n[1])
    geo4[i, 2] = wp.vector(n[2], a[0], a[1], a[2])
    geo4[i, 3] = wp.vector(c2[0], c2[1], z, cutoff[i])
    nrm_face[i] = facing
    color[i] = surfel_color(sh, i, sh_degree, p - cam.center)


@wp.func
def pixel_tile_coords(g: int, tile_size: int, tiles_x: int):
    """Pixel (column, row) of thread ``g`` in tile-major order."""
    tpix = tile_size * tile_size
    tile = g // tpix
    local = g - tile * tpix
    px = (tile % tiles_x) * tile_size + local % tile_size
    py = (tile // tiles_x) * tile_size + local // tile_size
    return tile, px, py


@wp.func
def splat_hit(d: Any, U: Any, V: Any, n: Any, auv: Any, m2: Any, zc: Any, c: Any, pix: Any, fis: Any):
    """Ray-splat intersection and screen-space filter at one pixel for the fields of a :class:`SurfelRecord`
    (``U``, ``V``, ``n``, ``auv``, ``m2``, ``zc`` and the cut-off ``c``).

    With ``a = camera - centre`` and ``auv = (a.U, a.V, a.n)`` precomputed per surfel, the ray
    ``a + t d`` meets the plane at ``t = -a.n / d.n`` with local coordinates
    ``u = a.U + t d.U``, ``v = a.V + t d.V``. Returns ``(rho, z, branch3d, u, v, t, dU, dV, dn)``:
    the Gaussian exponent ``rho = min(rho3d, rho2d)``, the contribution's z-depth (intersection
    depth in the 3D branch, centre depth in the filter branch), which branch won, and the terms
    the adjoint reuses.

    A pair that is surely outside, ``rho2d > cutoff`` and ``rho3d > cutoff`` (tested without a division, as
    ``|(u, v)|^2 dn^2 > cutoff dn^2``), returns ``rho = RHO_BIG`` (above every cut-off) at once: most pairs of a
    tile's list are, and forward and backward take the same decision, so skipping them changes nothing but time.
    """
    dx = pix[0] - m2[0]
    dy = pix[1] - m2[1]
    rho2d = fis * (dx * dx + dy * dy)
    du = d[0] * U[0] + d[1] * U[1] + d[2] * U[2]
    dv = d[0] * V[0] + d[1] * V[1] + d[2] * V[2]
    dn = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
    zero = type(zc)(0.0)
    if rho2d > c:
        pu = auv[0] * dn - auv[2] * du
        pv = auv[1] * dn - auv[2] * dv
        if pu * pu + pv * pv > c * dn * dn:
            return type(zc)(RHO_BIG), zc, False, zero, zero, zero, du, dv, dn
    rho3d = type(zc)(RHO_BIG)
    t = zero
    u = zero
    v = zero
    if wp.abs(dn) > type(zc)(PARALLEL_EPS):
        t = -auv[2] / dn
        u = auv[0] + t * du
        v = auv[1] + t * dv
        r = u * u + v * v
        if wp.isfinite(r):
            rho3d = r
    branch3d = rho3d <= rho2d + type(zc)(RHO_TIE)
    rho = rho2d
    z = zc
    if branch3d:
        rho = rho3d
        z = t
    return rho, z, branch3d, u, v, t, du, dv, dn


@wp.kernel(enable_backward=False)
def pack_surfels_kernel(
    offset: int,
    uax: wp.array[Any],
    vax: wp.array[Any],
    nrm: wp.array[Any],
    auv: wp.array[Any],
    m2: wp.array[Any],
    zc: wp.array[Any],
    cutoff: wp.array[Any],
    geo: wp.array[Any],
):
    """Pack what the pixel kernels test for every (pixel, surfel) pair into one :class:`SurfelRecord` per surfel."""
    i = wp.tid() + offset
    rec = geo[i]  # a local of the record type (generic kernel); every field is overwritten
    rec.U = uax[i]
    rec.V = vax[i]
    rec.n = nrm[i]
    rec.auv = auv[i]
    rec.m2 = m2[i]
    rec.zc = zc[i]
    rec.cutoff = cutoff[i]
    geo[i] = rec


@wp.func
def record_hit(d: Any, g: Any, pix: Any, fis: Any):
    """:func:`splat_hit` for a :class:`SurfelRecord` ``g``."""
    return splat_hit(d, g.U, g.V, g.n, g.auv, g.m2, g.zc, g.cutoff, pix, fis)


@wp.func
def ndc_depth(z: Any, near: Any, far: Any):
    """2DGS distortion depth mapping ``far / (far - near) * (1 - near / z)`` and its derivative."""
    k = far / (far - near)
    return k * (type(z)(1.0) - near / z), k * near / (z * z)


@wp.kernel(enable_backward=False, cuda_max_registers=FWD_MAX_REGS)
def render_forward_kernel(
    offset: int,
    worker: int,
    tile_start: wp.array[wp.int32],
    tile_end: wp.array[wp.int32],
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
    visibility: wp.array2d[wp.int32],
):
    """Front-to-back compositing of one pixel over its tile's depth-sorted surfel list.

    With ``coop`` (CUDA) the 32 pixels of a warp walk the list together until every one of them has
    stopped, and a surfel's visibility count is one ballot over the warp and one atomic add.
    """
    cam = cams[0]
    tile, px, py = pixel_tile_coords(wp.tid() + offset, tile_size, tiles_x)
    # pixels past the image edge (partial tiles) still walk with their warp, writing nothing
    inside = px < rgb.shape[1] and py < rgb.shape[0]
    px = wp.min(px, rgb.shape[1] - 1)
    py = wp.min(py, rgb.shape[0] - 1)
    d = rays[py, px]
    f_ref = d[0]
    near = cam.near
    far = cam.far
    fis = cam.filter_inv_sq
    pix = wp.vector(type(f_ref)(px) + type(f_ref)(0.5), type(f_ref)(py) + type(f_ref)(0.5))
    zero = type(f_ref)(0.0)
    T = type(f_ref)(1.0)
    c = wp.vector(zero, zero, zero)
    nacc = wp.vector(zero, zero, zero)
    dsum = zero
    m1 = zero
    m2s = zero
    dist = zero
    med = zero
    med_k = int(-1)
    end = tile_start[tile]
    k_end = tile_end[tile]
    done = not inside
    lane = lane_id(coop)
    slab = staging_slab(f_ref)
    kb = tile_start[tile]
    while kb < k_end and warp_any(not done, coop):
        nb = wp.min(batch, k_end - kb)
        mine = fetch_batch(ids, kb, 1, nb, lane, color, nrm_face)
        stage_batch(slab, geo4, opacity, mine, lane, nb, coop)
        j = int(0)
        while j < nb and warp_any(not done, coop):
            k = kb + j
            i = warp_bcast(mine, j, coop)
            # flat branches: the pair's alpha in one level, its test as booleans, the compositing in one level.
            # Warp turns every assignment under nested ifs into a select per level for each loop-carried value,
            # which kept old and new copies of all the accumulators live (ptxas sm_90, float32: 120 registers
            # nested, 80 so written: three blocks of 256 threads an SM instead of two)
            a = zero
            z = zero
            if not done:
                U, V, n, auv, m2, zc, cut = staged_record(slab, geo4, i, j, coop)
                rho, zh, b3, u, v, t, du, dv, dn = splat_hit(d, U, V, n, auv, m2, zc, cut, pix, fis)
                z = zh
                if not (rho > cut):  # else alpha < 1/255 for sure: skip the exp (a = 0 fails the test below)
                    op = staged_opacity(slab, geo4, opacity, i, j, coop)
                    a = wp.min(type(f_ref)(ALPHA_MAX), op * wp.exp(type(f_ref)(-0.5) * rho))
            ok = not done and not (a < type(f_ref)(ALPHA_MIN) or z < near)
            test_t = T * (type(f_ref)(1.0) - a)
            stop = ok and test_t < type(f_ref)(T_MIN)
            hit = ok and not stop
            done = done or stop
            if hit:
                w = a * T
                c = c + w * color[i]
                nacc = nacc + w * nrm_face[i]
                dsum = dsum + w * z
                m, dm = ndc_depth(z, near, far)
                dist = dist + w * (m * m * (type(f_ref)(1.0) - T) + m2s - type(f_ref)(2.0) * m * m1)
                m1 = m1 + w * m
                m2s = m2s + w * m * m
                if T > type(f_ref)(0.5):  # noqa: SIM300  T is the running transmittance
                    med = z
                    med_k = k
                T = test_t
                end = k + 1
            if warp_any(hit, coop):
                warp_count(visibility, worker, i, hit, coop)
            j = j + 1
        kb = kb + nb
    if not inside:
        return
    acc = type(f_ref)(1.0) - T
    rgb[py, px] = c + T * background[0]
    alpha[py, px] = acc
    if acc > zero:
        depth[py, px] = dsum / acc
    else:
        depth[py, px] = zero
    median[py, px] = med
    normal[py, px] = nacc
    distortion[py, px] = dist
    t_final[py, px] = T
    sums[py, px] = wp.vector(dsum, m1, m2s)
    last[py, px] = end
    median_idx[py, px] = med_k


# one compile of this module with every overload (see kernels/rasterize_records.py)
for _kernel in (prepare_surfels_kernel, prepare_records_kernel, pack_surfels_kernel, render_forward_kernel):
    declare_float_overloads(_kernel)
