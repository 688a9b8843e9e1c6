# SPDX-License-Identifier: Apache-2.0
"""Warp kernel for :func:`wtopo.ops.oriented_points`: surfels -> weighted oriented sample points.

Generic over float32/float64 (``typing.Any`` arrays); differentiated by Warp's tape.
"""

from typing import Any

import warp as wp

from .rotation import quat_axes


@wp.kernel
def oriented_points_kernel(
    means: wp.array[Any],
    quats: wp.array[Any],
    scales: wp.array[Any],
    opacities: wp.array[Any],
    normal_sign: wp.array[Any],
    samples: int,
    offset: Any,
    opacity_threshold: Any,
    center_weight: Any,
    offset_weight: Any,
    eps: Any,
    points: wp.array[Any],
    normals: wp.array[Any],
    weights: wp.array[Any],
):
    """One thread per surfel; writes rows ``i*samples .. i*samples + samples - 1``."""
    i = wp.tid()
    ax, ay, az = quat_axes(quats[i], float(eps * eps))  # |q| <= eps: identity
    mu = means[i]
    s = scales[i]
    o = opacities[i]
    zero = type(o)(0.0)
    gate = zero
    if o >= opacity_threshold:
        gate = o
    nrm = az * normal_sign[i]
    base = i * samples
    points[base] = mu
    normals[base] = nrm
    weights[base] = gate * center_weight
    # Sample k in 1..4 sits at +x, -x, +y, -y of the tangent frame, at offset * scale.
    if samples > 1:
        dx = ax * (offset * s[0])
        dy = ay * (offset * s[1])
        wo = gate * offset_weight
        points[base + 1] = mu + dx
        points[base + 2] = mu - dx
        points[base + 3] = mu + dy
        points[base + 4] = mu - dy
        for k in range(1, 5):
            normals[base + k] = nrm
            weights[base + k] = wo
