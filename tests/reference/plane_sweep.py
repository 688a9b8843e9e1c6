# SPDX-License-Identifier: Apache-2.0
"""Torch reference of :func:`wtopo.plane_sweep.plane_costs`: the plane sweep's score as the sweep computed it
before the Warp kernels (each source warped into the reference on every plane with ``grid_sample``, window
moments by separable running sums), in any float dtype."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def box_sum(x: torch.Tensor, half: int, dim: int) -> torch.Tensor:
    """Sum over the ``2 half + 1`` run along ``dim`` centred on each entry (zero outside), by a running sum."""
    side = 2 * half + 1
    pad = [0, 0] * (x.ndim - 1 - (dim % x.ndim)) + [half + 1, half]
    c = torch.cumsum(F.pad(x, pad), dim=dim)
    n = x.shape[dim]
    return c.narrow(dim, side, n) - c.narrow(dim, 0, n)


def box(x: torch.Tensor, half: int) -> torch.Tensor:
    """Window mean over the last two dims [..., H, W], over each window's in-image pixels."""
    ones = torch.ones(x.shape[-2:], dtype=x.dtype, device=x.device)
    count = box_sum(box_sum(ones, half, -1), half, -2)
    return box_sum(box_sum(x, half, -1), half, -2) / count


def window_moments(gray: torch.Tensor, half: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference's window mean and variance [H, W] of ``gray``'s dtype (:class:`wtopo.plane_sweep.SweepReference`),
    summed in float64."""
    g = gray.double()
    mu = box(g, half)
    return mu.to(gray.dtype), (box(g * g, half) - mu * mu).clamp_min(0).to(gray.dtype)


def _project(params: torch.Tensor, p: torch.Tensor):
    """A source row's (``multiview_ncc`` layout) projection of points in its frame [..., 3] -> u, v, z."""
    z = p[..., 2]
    zs = torch.where(z.abs() < 1e-12, 1e-12, z)
    xn, yn = p[..., 0] / zs, p[..., 1] / zs
    if float(params[22]) != 0.0:
        k1, k2, p1, p2, k3 = params[17:22]
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xn, yn = (xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn),
                  yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn)
    return params[12] * xn + params[13] * yn + params[14], params[15] * yn + params[16], z


def plane_costs_torch(gray, mean, var, dirs, sources, params, planes, *, level=None, half=3, best=2,
                      min_texture=1e-4, details=False):
    """``[P, H, W]``: the same arguments as :func:`wtopo.plane_sweep.plane_costs` (``level``: ``(camera_height,
    rate, lo, hi)`` when ``planes`` are level planes' heights). ``details``: also a dict of the per-source
    intermediates ``[P, K, H, W]`` (``ncc``, the source window's variance ``var_s``, the centre's ``u``, ``v``,
    ``z``), for tests that leave out the entries a threshold could flip by round-off."""
    K, H, W = sources.shape
    if level is None:
        depth = (1.0 / planes)[:, None, None].expand(-1, H, W)
    else:
        a, b, lo, hi = level
        b = torch.where(b.abs() < 1e-6, 1e-6, b)
        depth = (planes[:, None, None] - a) / b
        depth = torch.where((depth >= lo) & (depth <= hi), depth, -1.0)
    P = planes.shape[0]
    r = gray[None, None]
    warped, valid, uvz = [], [], []
    for k in range(K):
        R, o = params[k, :9].reshape(3, 3), params[k, 9:12]
        q = dirs @ R.T  # [H, W, 3]
        u, v, z = _project(params[k], o + depth[..., None] * q)
        g = torch.stack([u / W * 2 - 1, v / H * 2 - 1], dim=-1)
        w = F.grid_sample(sources[k][None, None].expand(P, -1, -1, -1), g, mode="bilinear", padding_mode="zeros",
                          align_corners=False)[:, 0]
        warped.append(w)
        uvz.append(torch.stack([u, v, z]))
        valid.append((z > 0) & (depth > 0) & (u >= 0) & (u <= W) & (v >= 0) & (v <= H))
    w = torch.stack(warped, 1)  # [P, K, H, W]
    ok = torch.stack(valid, 1)
    flat = w.reshape(P * K, 1, H, W)
    mu_s = box(flat, half)
    var_s = (box(flat * flat, half) - mu_s * mu_s).clamp_min(0)
    cov = box(flat * r, half) - mu_s * mean
    ncc = (cov / torch.sqrt(var_s * var + 1e-12)).reshape(P, K, H, W)
    ncc = torch.where(ok & (var_s.reshape(P, K, H, W) > min_texture), ncc, -1.0)
    cost = ncc.topk(best, dim=1).values.mean(1)
    if not details:
        return cost
    u, v, z = torch.stack(uvz, 2)  # [P, K, H, W] each
    return cost, {"ncc": ncc, "var_s": var_s.reshape(P, K, H, W), "u": u, "v": v, "z": z}
