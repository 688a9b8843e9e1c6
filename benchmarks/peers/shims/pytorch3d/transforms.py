# SPDX-License-Identifier: Apache-2.0
"""``pytorch3d.transforms``' quaternion <-> rotation matrix conversions, with its conventions.

Quaternions are real part first, ``(w, x, y, z)``, Hamilton product, acting as ``R @ v`` on column
vectors. ``quaternion_to_matrix`` accepts unnormalised quaternions (it divides by the squared norm);
``matrix_to_quaternion`` picks the best-conditioned of the four square-root branches and returns the
quaternion with a non-negative real part (as pytorch3d >= 0.7.5 does).
"""

from __future__ import annotations

import torch

__all__ = ["matrix_to_quaternion", "quaternion_to_matrix"]


def quaternion_to_matrix(quaternions: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] (real part first, any non-zero norm)."""
    w, x, y, z = torch.unbind(quaternions, -1)
    s = 2.0 / (quaternions * quaternions).sum(-1)
    rows = (
        1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y),
        s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x),
        s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y),
    )
    return torch.stack(rows, -1).reshape(quaternions.shape[:-1] + (3, 3))


def _sqrt_positive(x: torch.Tensor) -> torch.Tensor:
    """sqrt(max(x, 0)) with a zero gradient where x <= 0."""
    out = torch.zeros_like(x)
    pos = x > 0
    out[pos] = torch.sqrt(x[pos])
    return out


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """Quaternions [..., 4] (real part first, real part >= 0) of rotation matrices [..., 3, 3]."""
    if matrix.size(-1) != 3 or matrix.size(-2) != 3:
        raise ValueError(f"invalid rotation matrix shape {tuple(matrix.shape)}")
    batch = matrix.shape[:-2]
    m = matrix.reshape(batch + (9,))
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = torch.unbind(m, -1)
    # 4 q_c^2 for c = w, x, y, z (the diagonal of the 4x4 symmetric form), and 2 |q_c|
    two_abs = _sqrt_positive(torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                                          1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1))
    # row c holds 4 q_c * (w, x, y, z); its diagonal entry 4 q_c^2 is taken as (2 |q_c|)^2
    rows = torch.stack([
        torch.stack([two_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, two_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
        torch.stack([m02 - m20, m10 + m01, two_abs[..., 2] ** 2, m12 + m21], -1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, two_abs[..., 3] ** 2], -1),
    ], -2)
    # dividing row c by 4 |q_c| gives (w, x, y, z) up to sign; the floor only guards the rows not chosen
    cand = rows / (2.0 * two_abs[..., None].clamp_min(0.1))
    best = two_abs.argmax(-1)
    q = torch.gather(cand, -2, best[..., None, None].expand(batch + (1, 4))).squeeze(-2)
    return torch.where(q[..., :1] < 0, -q, q)
