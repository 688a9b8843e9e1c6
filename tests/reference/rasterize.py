# SPDX-License-Identifier: Apache-2.0
"""Pure-torch brute-force reference of :func:`wtopo.ops.rasterize_surfels`.

Every surfel is evaluated at every pixel ([P, N] tensors) with the same maths as the Warp kernels
(ray-splat intersection, screen-space filter, alpha clamp and skips, compositing in the order of
the centres' z-depth, early stop); differentiable by torch autograd. No tiles: a conservative
binning must give the same image.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def quat_axes_ref(q):
    """Tangent axes and normal [N, 3] each of (w, x, y, z) quaternions of any norm (|q|^2 < 1e-30: identity)."""
    n2 = (q * q).sum(-1, keepdim=True)
    small = n2 < 1e-30
    ident = torch.zeros_like(q)
    ident[:, 0] = 1
    q = torch.where(small, ident, q / torch.sqrt(torch.where(small, torch.ones_like(n2), n2)))
    w, x, y, z = q.unbind(-1)
    tu = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], -1)
    tv = torch.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], -1)
    n = torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)
    return tu, tv, n


def sh_color_ref(sh, degree, d):
    """3DGS SH colour max(SH(d) + 0.5, 0) for coefficients [N, K, 3] and unit directions [N, 3]."""
    x, y, z = (d[:, i:i + 1] for i in range(3))
    c = SH_C0 * sh[:, 0]
    if degree > 0:
        c = c - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        c = (c + SH_C2[0] * x * y * sh[:, 4] + SH_C2[1] * y * z * sh[:, 5] + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
             + SH_C2[3] * x * z * sh[:, 7] + SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree > 2:
        c = (c + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9] + SH_C3[1] * x * y * z * sh[:, 10]
             + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
             + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
             + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15])
    return torch.clamp_min(c + 0.5, 0.0)


def project_ref(camera, pc, K, dist):
    """Pixel coordinates [N, 2] of camera-frame points [N, 3] (z > 0) with OpenCV distortion."""
    x = pc[:, 0] / pc[:, 2]
    y = pc[:, 1] / pc[:, 2]
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)


def rasterize_reference(means, quats, scales, opacities, colors_or_sh, camera, *, near, far, sh_degree=None,
                        background=None, shift=None, pixels=None, filter_sigma=2.0 ** -0.5):
    """Brute-force render; returns a dict of rgb, alpha, depth, median_depth, normal, distortion, visibility.

    ``shift`` [N, 2] translates each footprint on screen (pixels; its gradient at 0 is the
    screen-space gradient of the op's ``means2d``). ``pixels`` (flat indices) renders a subset:
    images then have shape [P, ...] instead of [H, W, ...].
    """
    dt, dev = means.dtype, means.device
    n = means.shape[0]
    H, W = camera.height, camera.width
    R = torch.as_tensor(camera.R, dtype=dt, device=dev)
    t = torch.as_tensor(camera.t, dtype=dt, device=dev)
    K = torch.as_tensor(camera.K, dtype=dt, device=dev)
    o = torch.as_tensor(camera.center, dtype=dt, device=dev)
    dist = [float(v) for v in (camera.distortion if camera.distortion is not None else [0.0] * 5)]
    _, dirs = camera.pixel_rays(dev, dt)
    dirs = dirs.reshape(-1, 3)
    idx = torch.arange(H * W, device=dev) if pixels is None else pixels
    d = dirs[idx]
    pix = torch.stack([(idx % W).to(dt) + 0.5, (idx // W).to(dt) + 0.5], -1)

    tu, tv, nrm = quat_axes_ref(quats)
    su = scales[:, 0].clamp_min(1e-30)
    sv = scales[:, 1].clamp_min(1e-30)
    U = tu / su[:, None]
    V = tv / sv[:, None]
    pc = means @ R.T + t
    zc = pc[:, 2]
    valid = zc > near
    pc_safe = torch.where(valid[:, None], pc, torch.ones_like(pc))
    m2 = project_ref(camera, pc_safe, K, dist)
    view = means - o
    nf = torch.where(((nrm * view).sum(-1) > 0)[:, None], -nrm, nrm)
    if colors_or_sh.ndim == 2:
        col = colors_or_sh
    else:
        deg = sh_degree if sh_degree is not None else int(round(colors_or_sh.shape[1] ** 0.5)) - 1
        vl2 = (view * view).sum(-1, keepdim=True)
        far_enough = vl2 > 1e-30
        vdir = torch.where(far_enough, view / torch.sqrt(torch.where(far_enough, vl2, torch.ones_like(vl2))),
                           torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=dev))
        col = sh_color_ref(colors_or_sh, deg, vdir)

    if shift is None:
        shift = torch.zeros(n, 2, dtype=dt, device=dev)
    kinv = torch.linalg.inv(K)[:2, :2]
    dshift_cam = torch.cat([shift @ kinv.T, torch.zeros(n, 1, dtype=dt, device=dev)], -1)  # [N, 3]
    dd = d[:, None, :] - (dshift_cam @ R)[None]  # [P, N, 3]: R^T applied per surfel
    a = o - means  # [N, 3]
    dn = (dd * nrm[None]).sum(-1)
    an = (a * nrm).sum(-1)
    parallel = dn.abs() <= 1e-12
    tt = -an[None] / torch.where(parallel, torch.ones_like(dn), dn)
    x = a[None] + tt[..., None] * dd
    u = (x * U[None]).sum(-1)
    v = (x * V[None]).sum(-1)
    rho3d = u * u + v * v
    rho3d = torch.where(parallel | ~torch.isfinite(rho3d), torch.full_like(rho3d, 1e30), rho3d)
    diff = pix[:, None, :] - (m2 + shift)[None]
    rho2d = (diff * diff).sum(-1) / filter_sigma**2
    b3 = rho3d <= rho2d + 1e-9  # the kernel's RHO_TIE: ties at the centre ray go to the object-space branch
    rho = torch.where(b3, rho3d, rho2d)
    z = torch.where(b3, tt, zc[None].expand_as(tt))
    alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * rho), max=0.99)
    ok = (alpha >= 1.0 / 255.0) & (z >= near) & valid[None]

    order = torch.argsort(zc.detach(), stable=True)
    alpha, ok, z = alpha[:, order], ok[:, order], z[:, order]
    a_ok = torch.where(ok, alpha, torch.zeros_like(alpha))
    ones = torch.ones_like(alpha[:, :1])
    t_before = torch.cat([ones, torch.cumprod(1 - a_ok, 1)[:, :-1]], 1)
    stop = ok & (t_before * (1 - a_ok) < 1e-4)
    include = ok & (torch.cumsum(stop.to(torch.int64), 1) == 0)
    a_in = torch.where(include, alpha, torch.zeros_like(alpha))
    tb = torch.cat([ones, torch.cumprod(1 - a_in, 1)[:, :-1]], 1)
    w = a_in * tb
    t_end = torch.prod(1 - a_in, 1)
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else torch.as_tensor(background, dtype=dt,
                                                                                         device=dev)
    rgb = w @ col[order] + t_end[:, None] * bg
    acc = 1 - t_end
    dsum = (w * torch.where(include, z, torch.zeros_like(z))).sum(1)
    has = acc > 0
    depth = torch.where(has, dsum / torch.where(has, acc, torch.ones_like(acc)), torch.zeros_like(acc))
    normal = w @ nf[order]
    z_safe = torch.where(include, z, torch.ones_like(z))
    m = far / (far - near) * (1 - near / z_safe)
    s_b = torch.cumsum(w, 1) - w
    m1_b = torch.cumsum(w * m, 1) - w * m
    m2_b = torch.cumsum(w * m * m, 1) - w * m * m
    distortion = (w * (m * m * s_b + m2_b - 2 * m * m1_b)).sum(1)
    mask = include & (tb > 0.5)
    ar = torch.arange(n, device=dev).expand_as(mask)
    last = torch.where(mask, ar, torch.full_like(ar, -1)).max(1).values if n else torch.full((len(idx),), -1,
                                                                                             device=dev)
    med = torch.gather(z_safe, 1, last.clamp_min(0)[:, None])[:, 0] if n else torch.zeros_like(acc)
    median = torch.where(last >= 0, med, torch.zeros_like(med))
    vis = torch.zeros(n, dtype=torch.int64, device=dev)
    vis[order] = include.sum(0)
    out = dict(rgb=rgb, alpha=acc, depth=depth, median_depth=median, normal=normal, distortion=distortion,
               visibility=vis, means2d=m2)
    if pixels is None:
        out = {k: (v.reshape(H, W, *v.shape[1:]) if k not in ("visibility", "means2d") else v) for k, v in out.items()}
    return out
