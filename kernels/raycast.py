# SPDX-License-Identifier: Apache-2.0
"""Warp kernels for BVH ray casting of a triangle mesh and nearest-face queries.

Two stages (``wtopo/raycast.py`` drives them):

* discrete (``enable_backward=False``): :func:`cast_packets_kernel` finds the first hit of every
  ray, 4 coherent rays per BVH sweep, with a conservative traversal and Woop's watertight test
  (float32 BVH); :func:`cast_rays_kernel` does the same per ray with ``wp.mesh_query_ray``, which
  is not conservative (kept for comparison); :func:`closest_faces_kernel` runs
  ``wp.mesh_query_point_no_sign``;
* differentiable: :func:`shade_hits_kernel` recomputes depth (ray-plane intersection) and the unit
  face normal from the hit triangle's three vertices in the caller's precision, so both carry
  gradients w.r.t. the vertices through Warp's generated adjoint.
"""

from typing import Any

import warp as wp

__all__ = ["cast_rays_kernel", "cast_packets_kernel", "closest_faces_kernel", "shade_hits_kernel"]


@wp.func
def _edge(ax: float, ay: float, bx: float, by: float):
    """``ax * by - ay * bx`` in float64: the float32 products are exact there, so the sign is exact
    and the value is exactly negated for the neighbouring triangle sharing the edge (watertight)."""
    return wp.float64(ax) * wp.float64(by) - wp.float64(ay) * wp.float64(bx)


@wp.func
def _woop_hit(o: wp.vec3, kx: int, ky: int, kz: int, sx: float, sy: float, sz: float,
              a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Watertight ray-triangle test (Woop, Benthin, Wald 2013) with the ray shear precomputed.

    Returns ``(hit, t, u, v)``; ``u``, ``v`` weight the first and second vertex.
    """
    pa = a - o
    pb = b - o
    pc = c - o
    ax = pa[kx] - sx * pa[kz]
    ay = pa[ky] - sy * pa[kz]
    bx = pb[kx] - sx * pb[kz]
    by = pb[ky] - sy * pb[kz]
    cx = pc[kx] - sx * pc[kz]
    cy = pc[ky] - sy * pc[kz]
    eu = _edge(cx, cy, bx, by)
    ev = _edge(ax, ay, cx, cy)
    ew = _edge(bx, by, ax, ay)
    zero = wp.float64(0.0)
    hit = True
    if (eu < zero or ev < zero or ew < zero) and (eu > zero or ev > zero or ew > zero):
        hit = False
    det = eu + ev + ew
    if det == zero:
        hit = False
    t = float(0.0)
    u = float(0.0)
    v = float(0.0)
    if hit:
        tt = (eu * wp.float64(sz * pa[kz]) + ev * wp.float64(sz * pb[kz]) + ew * wp.float64(sz * pc[kz])) / det
        if tt < zero:
            hit = False
        t = float(tt)
        u = float(eu / det)
        v = float(ev / det)
    return hit, t, u, v


@wp.kernel(enable_backward=False)
def cast_rays_kernel(
    offset: int,
    mesh: wp.uint64,
    origins: wp.array[wp.vec3],
    directions: wp.array[wp.vec3],
    max_t: float,
    face_id: wp.array[wp.int32],
    bary: wp.array[wp.vec2],
):
    """First hit of ray ``offset + tid``; face -1 and bary 0 on a miss."""
    i = wp.tid() + offset
    q = wp.mesh_query_ray(mesh, origins[i], directions[i], max_t)
    if q.result:
        face_id[i] = q.face
        # Woop's u, v are the weights of the triangle's first and second vertex.
        bary[i] = wp.vec2(q.u, q.v)
    else:
        face_id[i] = -1
        bary[i] = wp.vec2(0.0, 0.0)


@wp.func
def _shear(d: wp.vec3):
    """Axes and shear constants of the watertight test for direction ``d`` (kz = dominant axis)."""
    kz = int(0)
    if wp.abs(d[1]) > wp.abs(d[kz]):
        kz = 1
    if wp.abs(d[2]) > wp.abs(d[kz]):
        kz = 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    if d[kz] < 0.0:
        tmp = kx
        kx = ky
        ky = tmp
    sz = 1.0 / d[kz]
    return kx, ky, kz, d[kx] * sz, d[ky] * sz, sz


@wp.kernel(enable_backward=False)
def cast_packets_kernel(
    offset: int,
    mesh: wp.uint64,
    packets: wp.array2d[wp.int32],
    origins: wp.array[wp.vec3],
    directions: wp.array[wp.vec3],
    bounds: wp.array[wp.vec3],
    pad_rel: float,
    face_id: wp.array[wp.int32],
    bary: wp.array[wp.vec2],
):
    """First hits of the (up to) 4 rays of packet ``offset + tid`` (``packets[p]``, -1 = unused).

    ``wp.mesh_query_ray``'s slab test is not conservative: a ray through a vertex or an edge lying on
    a face of its leaf boxes can be rejected by rounding and go on to a farther surface or miss
    (measured: 0.25-1.7 % of rays aimed at the vertices of a closed mesh from inside). Here the BVH
    is swept per packet by capsules around the packet's mean ray, first up to the mesh's centre,
    then (only for rays still without a hit) on to the far side of the mesh (``bounds`` = lower,
    upper); each capsule's radius covers every ray of the packet over its segment plus a pad of
    ``pad_rel`` times the scene's coordinate scale. Warp inflates each box by that radius and uses
    the robust slab test, so no candidate is lost. Candidates go through the watertight test and
    the sweep is cut at the farthest of the packet's current closest hits. Sharing one traversal
    among 4 coherent rays also makes this ~35 % cheaper than ``wp.mesh_query_ray`` per ray
    (``benchmarks/raycast.md``).
    """
    p = wp.tid() + offset
    rid = wp.vec4i(packets[p, 0], packets[p, 1], packets[p, 2], packets[p, 3])
    oc = wp.vec3(0.0)
    dc = wp.vec3(0.0)
    cnt = float(0.0)
    for k in range(4):
        if rid[k] >= 0:
            oc += origins[rid[k]]
            dc += directions[rid[k]]
            cnt += 1.0
    if cnt == 0.0:
        return
    oc = oc / cnt
    dc = dc / cnt
    lo = bounds[0]
    hi = bounds[1]
    centre = 0.5 * (lo + hi)
    # the slab test's rounding error scales with the coordinates involved
    pad = pad_rel * (0.5 * wp.length(hi - lo) + wp.length(oc - centre) + wp.length(centre))
    half = 0.5 * wp.length(hi - lo) + pad
    # sweep length, in multiples of each ray's direction: past the far side of the mesh's sphere;
    # the 1 % (and 1e-6 for a degenerate zero reach) keep it strictly beyond after float32 rounding
    reach = float(0.0)
    for k in range(4):
        if rid[k] >= 0:
            dl = wp.length(directions[rid[k]])
            if dl > 0.0:
                reach = wp.max(reach, (wp.length(origins[rid[k]] - centre) + half) / dl)
    reach = reach * 1.01 + 1.0e-6
    # the point at parameter s*reach of ray k lies within spread_k(s) of the axis point at s
    offset_max = float(0.0)
    slope = float(0.0)
    for k in range(4):
        if rid[k] >= 0:
            offset_max = wp.max(offset_max, wp.length(origins[rid[k]] - oc))
            slope = wp.max(slope, reach * wp.length(directions[rid[k]] - dc))
    # two sweeps, up to the mesh's centre and beyond: the first, thinner capsule finds the
    # visible surface of an object in front of the camera with fewer candidates
    split = float(0.0)
    dcl = wp.length(dc)
    if dcl > 0.0:
        split = wp.clamp(wp.dot(centre - oc, dc) / (dcl * dcl) / reach, 0.0, 1.0)
    # per-ray shear constants of the watertight test
    ax_x = wp.vec4i(0)
    ax_y = wp.vec4i(0)
    ax_z = wp.vec4i(0)
    sh_x = wp.vec4(0.0)
    sh_y = wp.vec4(0.0)
    sh_z = wp.vec4(0.0)
    live = wp.vec4i(0)
    for k in range(4):
        if rid[k] >= 0:
            d = directions[rid[k]]
            kx, ky, kz, sx, sy, sz = _shear(d)
            if d[kz] != 0.0:  # a zero direction hits nothing
                live[k] = 1
            ax_x[k] = kx
            ax_y[k] = ky
            ax_z[k] = kz
            sh_x[k] = sx
            sh_y[k] = sy
            sh_z[k] = sz
    best = wp.vec4(1.0)  # closest hit per ray, in units of the sweep (s = t / reach)
    found = wp.vec4i(-1)
    bu = wp.vec4(0.0)
    bv = wp.vec4(0.0)
    for seg in range(2):
        s0 = float(0.0)
        s1 = split
        if seg == 1:
            s0 = split
            s1 = 1.0
        # skip an empty segment, and the second once every live ray hit in the first
        done = True
        for k in range(4):
            if live[k] == 1 and found[k] < 0:
                done = False
        if s1 <= s0 or done:
            continue
        radius = pad + offset_max + slope * s1
        span = s1 - s0
        query = wp.bvh_query_capsule(wp.mesh_get_bvh(mesh), oc + dc * (reach * s0), dc * (reach * span), radius)
        limit = float(1.0)  # in units of this segment
        f = int(0)
        while wp.bvh_query_next(query, f, limit):
            a = wp.mesh_get_point(mesh, 3 * f + 0)
            b = wp.mesh_get_point(mesh, 3 * f + 1)
            c = wp.mesh_get_point(mesh, 3 * f + 2)
            for k in range(4):
                if live[k] == 1:
                    hit, t, u, v = _woop_hit(origins[rid[k]], ax_x[k], ax_y[k], ax_z[k], sh_x[k], sh_y[k],
                                             sh_z[k], a, b, c)
                    if hit:
                        s = t / reach
                        # ties (a ray through a shared edge or vertex) keep the first face found
                        if s < best[k] or (found[k] < 0 and s <= best[k]):
                            best[k] = s
                            found[k] = f
                            bu[k] = u
                            bv[k] = v
            # cut the sweep once every live ray has a hit (monotonically shrinking, as Warp requires)
            all_hit = True
            far = float(0.0)
            for k in range(4):
                if live[k] == 1:
                    if found[k] < 0:
                        all_hit = False
                    far = wp.max(far, best[k])
            if all_hit:
                limit = wp.min(limit, (far - s0) / span)
    for k in range(4):
        if rid[k] >= 0:
            face_id[rid[k]] = found[k]
            bary[rid[k]] = wp.vec2(bu[k], bv[k])  # 0 on a miss


@wp.kernel(enable_backward=False)
def closest_faces_kernel(
    offset: int,
    mesh: wp.uint64,
    points: wp.array[wp.vec3],
    max_distance: float,
    face_id: wp.array[wp.int32],
    distance: wp.array[float],
    closest: wp.array[wp.vec3],
):
    """Nearest face of point ``offset + tid`` within ``max_distance``; face -1, distance inf, closest 0 otherwise."""
    i = wp.tid() + offset
    p = points[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_distance)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        face_id[i] = q.face
        distance[i] = wp.length(c - p)
        closest[i] = c
    else:
        face_id[i] = -1
        distance[i] = wp.inf


@wp.kernel
def shade_hits_kernel(
    offset: int,
    verts: wp.array[Any],
    faces: wp.array[wp.int32],
    face_id: wp.array[wp.int32],
    origins: wp.array[Any],
    directions: wp.array[Any],
    depth: wp.array[Any],
    normal: wp.array[Any],
):
    """Ray parameter and unit face normal of ray ``tid``'s hit triangle; outputs stay 0 on a miss.

    ``faces`` is the flattened ``[3F]`` index array.  ``depth`` is the ray parameter ``t`` of the
    plane through the triangle, ``t = <a - o, n> / <d, n>``, invariant to the length of ``n``.
    """
    i = wp.tid() + offset
    f = face_id[i]
    if f >= 0:
        a = verts[faces[3 * f + 0]]
        b = verts[faces[3 * f + 1]]
        c = verts[faces[3 * f + 2]]
        n = wp.cross(b - a, c - a)
        l2 = wp.dot(n, n)
        # 1e-30 keeps sqrt and its adjoint finite for a zero-area triangle (never hit by the
        # watertight test, but float64 vertices may degenerate differently from the float32 BVH);
        # it is far below the squared doubled area of any triangle the float32 BVH can resolve.
        inv_len = type(l2)(1.0) / wp.sqrt(wp.max(l2, type(l2)(1.0e-30)))
        denom = wp.dot(directions[i], n)
        # A hit implies denom != 0 in float32; keep its sign and bound it away from 0 so a grazing
        # hit re-evaluated in another precision stays finite.
        tiny = type(l2)(1.0e-30)
        zero = type(l2)(0.0)
        denom = wp.where(wp.abs(denom) < tiny, wp.where(denom < zero, -tiny, tiny), denom)
        depth[i] = wp.dot(a - origins[i], n) / denom
        normal[i] = n * inv_len
