# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference for ``wtopo.ops.oriented_points``."""

import torch


def quat_to_rotation(q: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] (columns = local axes) of (w, x, y, z) quaternions; |q| < eps -> identity."""
    norm = q.norm(dim=1, keepdim=True)
    small = norm < eps
    identity = torch.tensor([1.0, 0, 0, 0], dtype=q.dtype, device=q.device)
    qn = torch.where(small, identity, q / torch.where(small, 1.0, norm))
    w, x, y, z = qn.unbind(1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, 1) for r in rows], 1)


def oriented_points_ref(means, quats, scales, opacities, *, samples=5, offset=0.5, opacity_threshold=0.0,
                        center_weight=1.0, offset_weight=0.5, normal_sign=None):
    """Return (points [N*S, 3], normals [N*S, 3], weights [N*S]) as documented for the op."""
    rot = quat_to_rotation(quats)
    ax, ay, az = rot[:, :, 0], rot[:, :, 1], rot[:, :, 2]
    nrm = az if normal_sign is None else az * normal_sign.to(az.dtype)[:, None]
    gate = torch.where(opacities >= opacity_threshold, opacities, torch.zeros_like(opacities))
    if samples == 1:
        return means, nrm, gate * center_weight
    dx = ax * (offset * scales[:, :1])
    dy = ay * (offset * scales[:, 1:])
    pts = torch.stack([means, means + dx, means - dx, means + dy, means - dy], 1)
    w = torch.stack([gate * center_weight] + [gate * offset_weight] * 4, 1)
    n = means.shape[0]
    return pts.reshape(n * 5, 3), nrm[:, None].expand(n, 5, 3).reshape(n * 5, 3), w.reshape(n * 5)
