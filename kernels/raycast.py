# SPDX-License-Identifier: Apache-2.0
"""Warp kernels for BVH ray casting of a triangle mesh and nearest-face queries.

Two stages (``wtopo/raycast.py`` drives them):

* discrete (``enable_backward=False``): :func:`cast_rays_kernel` finds the first hit of every
  ray with ``wp.mesh_query_ray`` (watertight Woop test, float32 BVH) and writes the face id and
  barycentrics; :func:`closest_faces_kernel` runs ``wp.mesh_query_point_no_sign``;
* differentiable: :func:`shade_hits_kernel` recomputes depth (ray-plane intersection) and the unit
  face normal from the hit triangle's three vertices in the caller's precision, so both carry
  gradients w.r.t. the vertices through Warp's generated adjoint.
"""

from typing import Any

import warp as wp

__all__ = ["cast_rays_kernel", "closest_faces_kernel", "shade_hits_kernel"]


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
    """First hit of ray ``offset + tid``; face -1 and bary 0 on a miss (outputs start zeroed)."""
    i = wp.tid() + offset
    q = wp.mesh_query_ray(mesh, origins[i], directions[i], max_t)
    if q.result:
        face_id[i] = q.face
        # Woop's u, v are the weights of the triangle's first and second vertex.
        bary[i] = wp.vec2(q.u, q.v)
    else:
        face_id[i] = -1


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
    i = wp.tid()
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
