# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference of the multi-view patch NCC cost (:mod:`wtopo.fitting.multiview`), written directly.

Independent of the module's shortcuts (per-view window statistics, one ray origin per view, points
moved into the source camera by ray): every window pixel's ray is intersected with the plane in world
coordinates, projected by :meth:`wtopo.Camera`'s own model (re-implemented here in torch), sampled
bilinearly, and its grey levels centred per window; torch autograd gives the gradient.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["plane_costs_reference", "plane_costs_torch", "multiview_loss_torch"]

_GRAY = (0.299, 0.587, 0.114)


def _project(cam, y):
    R = torch.as_tensor(cam.R, dtype=y.dtype)
    t = torch.as_tensor(cam.t, dtype=y.dtype)
    p = y @ R.T + t
    z = p[..., 2]
    xn, yn = p[..., 0] / z, p[..., 1] / z
    if cam.distortion is not None:
        k1, k2, p1, p2, k3 = (float(v) for v in cam.distortion)
        r2 = xn * xn + yn * yn
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xn, yn = (xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn),
                  yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn)
    K = cam.K
    return K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2], z


def plane_costs_reference(cameras, images, vi: int, py, px, depth, normal, pick, half: int):
    """Per window ``1 - NCC`` [P, len(pick)] of the ``(2 half + 1)^2`` windows centred on pixels ``(py, px)`` of
    view ``vi`` mapped through the planes of z-depth ``depth`` [P] and normal ``normal`` [P, 3] into the views
    ``pick``, clamped to [0, 2]; 2 where a window point falls outside a view or behind it."""
    dt = depth.dtype
    ref = cameras[vi]
    o, d = ref.pixel_rays("cpu", dt)
    r = torch.arange(-half, half + 1)
    qy = py[:, None] + r.repeat_interleave(len(r))[None]
    qx = px[:, None] + r.repeat(len(r))[None]
    g = torch.tensor(_GRAY, dtype=dt)
    rv = images[vi].to(dt)[qy, qx] @ g
    rc = rv - rv.mean(1, keepdim=True)
    n = normal / normal.norm(dim=-1, keepdim=True)
    x = o[py, px] + d[py, px] * depth[:, None]
    oq, dq = o[qy, qx], d[qy, qx]
    t = ((x[:, None] - oq) * n[:, None]).sum(-1) / (dq * n[:, None]).sum(-1)
    y = oq + dq * t[..., None]
    out = []
    for j in pick:
        cam = cameras[j]
        u, v, z = _project(cam, y)
        img = images[j].to(dt) @ g
        grid = torch.stack([u / cam.width * 2 - 1, v / cam.height * 2 - 1], -1)
        sv = F.grid_sample(img[None, None], grid[None], mode="bilinear", padding_mode="border",
                           align_corners=False)[0, 0]
        sc = sv - sv.mean(1, keepdim=True)
        ncc = (rc * sc).mean(1) / ((rc * rc).mean(1) * (sc * sc).mean(1) + 1e-6).sqrt()
        inside = ((z > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)).all(1)
        out.append(torch.where(inside, (1.0 - ncc).clamp(0.0, 2.0), torch.full_like(ncc, 2.0)))
    return torch.stack(out, 1)


def plane_costs_torch(mv, vi: int, py, px, depth, normal, alpha, pick):
    """The term's torch formulation before the Warp kernel, op for op: ``(best cost [P], ok [P] bool)`` of the
    windows centred on ``(py, px)`` of view ``vi`` of the :class:`~wtopo.fitting.multiview.MultiViewNCC`
    ``mv``, through the planes of the maps ``depth`` [H, W] and ``normal`` [H, W, 3], covered where ``alpha``
    [H, W] is at least one half. Uses ``mv``'s cached per-view statistics and cameras."""
    from wtopo.fitting import multiview as M

    h = mv.half
    r = torch.arange(-h, h + 1, device=py.device)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    qy, qx = py[:, None] + dy.reshape(-1)[None], px[:, None] + dx.reshape(-1)[None]  # [P, K]
    ref = mv._cam(vi, py.device)
    st = mv._view_stats(vi, py.device)
    rc = st.gray[qy, qx] - st.mean[py, px][:, None]
    rvar = st.var[py, px]
    dq, length, textured = st.dirs[qy, qx], st.length[qy, qx], rvar.sqrt() >= M._MIN_STD
    d, n = depth[py, px], normal[py, px]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    den = (dq * n[:, None]).sum(-1)
    with torch.no_grad():
        ok = (d > 0) & ((den / length).abs().amin(1) > M._GRAZING) & textured & (alpha.detach()[py, px] >= 0.5)
    den = torch.where(den.abs() < 1e-8, torch.full_like(den, 1e-8), den)
    t = (d * (ref.dirs[py, px] * n).sum(-1))[:, None] / den
    costs = []
    for j in pick:
        src = mv._cam(j, d.device)
        u, v, z = src.project_camera(src.R @ ref.origin[0, 0] + src.t + t[..., None] * (dq @ src.R.T))
        with torch.no_grad():
            inside = ((z > 0) & (u >= 0) & (u <= src.W) & (v >= 0) & (v <= src.H)).all(1)
        sv = F.grid_sample(mv._gray_of(j)[None, None], src.grid(u, v)[None], mode="bilinear",
                           padding_mode="border", align_corners=False)[0, 0]
        sc = sv - sv.mean(1, keepdim=True)
        ncc = (rc * sc).mean(1) / (rvar * (sc * sc).mean(1) + M._NCC_EPS).sqrt()
        cost = (1.0 - ncc).clamp(0.0, 2.0)
        costs.append(torch.where(inside, cost, torch.full_like(cost, 2.0)))
    return torch.stack(costs).amin(0), ok


def multiview_loss_torch(mv, it: int, vi: int, median_depth, normal, alpha):
    """``mv(it, vi, median_depth, normal, alpha)`` with the windows scored by :func:`plane_costs_torch`: the
    same pixels, neighbours and masks."""
    from wtopo.fitting import multiview as M

    dev = median_depth.device
    H, W = median_depth.shape
    h = mv.half
    seed = mv.seed * 1_000_003 + it
    g = torch.Generator(dev).manual_seed(seed)
    count = mv.count(H, W)
    py = torch.randint(h, H - h, (count,), generator=g, device=dev)
    px = torch.randint(h, W - h, (count,), generator=g, device=dev)
    best, ok = plane_costs_torch(mv, vi, py, px, median_depth, normal, alpha, mv._pick(vi, seed))
    w = (ok & (best.detach() < M._MAX_COST)).to(best.dtype)
    return (best * w).sum() / w.sum().clamp_min(1.0)
