# SPDX-License-Identifier: Apache-2.0
"""Brute-force torch reference for mesh ray casting (Moller-Trumbore over every ray x triangle).

Differentiable by torch autograd w.r.t. the vertices (for small meshes: memory is rays x faces).
"""

from __future__ import annotations

import torch

__all__ = ["raycast_reference", "closest_point_reference"]


def raycast_reference(verts: torch.Tensor, faces: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor,
                      *, det_eps: float = 0.0):
    """First hit of every ray against every triangle.

    Args:
        verts: [V, 3] float vertex positions.
        faces: [F, 3] int vertex indices of each triangle.
        origins: [..., 3] ray origins, same dtype as verts.
        directions: [..., 3] ray directions (not necessarily unit: ``depth`` is in their units),
            same dtype as verts.
        det_eps: rays with ``|det| <= det_eps`` (parallel to the triangle) miss it.

    Returns:
        dict with ``depth`` [...] (ray parameter t, 0 on misses), ``normal`` [..., 3] (unit face
        normal by winding, 0 on misses), ``face_id`` [...] int64 (-1 on misses), ``bary`` [..., 2]
        (weights of the face's first and second vertex), ``mask`` [...] bool.
    """
    shape = origins.shape[:-1]
    o = origins.reshape(-1, 1, 3)
    d = directions.reshape(-1, 1, 3)
    a, b, c = (verts[faces[:, k].long()][None] for k in range(3))  # [1, F, 3]
    e1, e2 = b - a, c - a
    shp = (o.shape[0], a.shape[1], 3)
    d = d.expand(shp)
    p = torch.cross(d, e2.expand(shp), dim=-1)
    det = (e1 * p).sum(-1)
    ok = det.abs() > det_eps
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    s = o - a
    u = (s * p).sum(-1) * inv
    q = torch.cross(s, e1.expand(shp), dim=-1)
    v = (d * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0)
    big = torch.full_like(t, float("inf"))
    t_hit = torch.where(hit, t, big)
    tmin, fid = t_hit.min(dim=1)
    mask = torch.isfinite(tmin)
    fid = torch.where(mask, fid, torch.full_like(fid, -1))
    rows = torch.arange(t.shape[0], device=t.device)
    fsafe = fid.clamp_min(0)
    depth = torch.where(mask, t[rows, fsafe], torch.zeros_like(tmin))
    n = torch.cross(e1[0], e2[0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    normal = torch.where(mask[:, None], n[fsafe], torch.zeros_like(n[fsafe]))
    # Moller-Trumbore's u, v weight the second and third vertex: hit = (1-u-v) a + u b + v c
    uu, vv = u[rows, fsafe], v[rows, fsafe]
    bary = torch.stack([1 - uu - vv, uu], -1) * mask[:, None]
    return {
        "depth": depth.reshape(shape),
        "normal": normal.reshape(*shape, 3),
        "face_id": fid.reshape(shape),
        "bary": bary.reshape(*shape, 2),
        "mask": mask.reshape(shape),
    }


def closest_point_reference(verts, faces, points):
    """Brute-force closest point on a triangle mesh (Ericson, Real-Time Collision Detection 5.1.5).

    Args:
        verts: [V, 3] float64 array of vertex positions.
        faces: [F, 3] int array of vertex indices of each triangle.
        points: [P, 3] float64 array of query points.

    Returns:
        ``(face_id [P], distance [P], closest [P, 3])`` NumPy arrays (memory is P x F).
    """
    import numpy as np

    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)[:, None, :]
    a, b, c = v[f[:, 0]][None], v[f[:, 1]][None], v[f[:, 2]][None]
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda x, y: (x * y).sum(-1)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        res = a + ab * v_in[..., None] + ac * w_in[..., None]  # interior
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        res = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + (c - b) * t_bc[..., None], res)
        res = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * (d2 / (d2 - d6))[..., None], res)
        res = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * (d1 / (d1 - d3))[..., None], res)
        res = np.where(((d6 >= 0) & (d5 <= d6))[..., None], np.broadcast_to(c, res.shape), res)
        res = np.where(((d3 >= 0) & (d4 <= d3))[..., None], np.broadcast_to(b, res.shape), res)
        res = np.where(((d1 <= 0) & (d2 <= 0))[..., None], np.broadcast_to(a, res.shape), res)
    dist = np.linalg.norm(res - p, axis=-1)
    fid = dist.argmin(1)
    rows = np.arange(p.shape[0])
    return fid, dist[rows, fid], res[rows, fid]
