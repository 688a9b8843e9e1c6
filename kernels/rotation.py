# SPDX-License-Identifier: Apache-2.0
"""Rotation helpers shared by the surfel kernels (oriented points, rasterizer, binning)."""

from typing import Any

import warp as wp


@wp.func
def quat_axes(q: Any, min_norm_sq: float):
    """Local x, y, z axes (the rotation's columns) of a (w, x, y, z) quaternion of any norm.

    A quaternion with ``|q|^2 <= min_norm_sq`` falls back to the identity rotation; its gradient
    is then exactly zero (each op documents its threshold). Generic over float32/float64.
    """
    one = type(q[0])(1.0)
    zero = type(q[0])(0.0)
    two = type(q[0])(2.0)
    n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    w = one
    x = zero
    y = zero
    z = zero
    if n2 > type(q[0])(min_norm_sq):
        inv = one / wp.sqrt(n2)
        w = q[0] * inv
        x = q[1] * inv
        y = q[2] * inv
        z = q[3] * inv
    ax = wp.vector(one - two * (y * y + z * z), two * (x * y + w * z), two * (x * z - w * y))
    ay = wp.vector(two * (x * y - w * z), one - two * (x * x + z * z), two * (y * z + w * x))
    az = wp.vector(two * (x * z + w * y), two * (y * z - w * x), one - two * (x * x + y * y))
    return ax, ay, az
