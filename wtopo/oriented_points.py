# SPDX-License-Identifier: Apache-2.0
"""Oriented, weighted sample points from Gaussian surfels (the input of the DPSR Poisson solve)."""

from __future__ import annotations

from typing import NamedTuple

import torch

from . import _bridge
from ._validate import require_finite, require_positive, require_same_device, require_tensor, value_checks
from .kernels.oriented_points import oriented_points_kernel

__all__ = ["OrientedPoints", "oriented_points"]

# Quaternions with norm below this are treated as the identity rotation. 1e-7 is far below any
# quaternion an optimiser produces and far above float32 denormals, so 1/|q| stays finite.
QUAT_EPS = 1e-7


class OrientedPoints(NamedTuple):
    """Weighted oriented sample points.

    Attributes:
        points: sample positions, shape ``[N*S, 3]``, dtype of ``means``, same units as ``means``.
        normals: unit normals, shape ``[N*S, 3]``.
        weights: non-negative weights, shape ``[N*S]``.
    """

    points: torch.Tensor
    normals: torch.Tensor
    weights: torch.Tensor


def _op(dtype: torch.dtype, samples: int, params: tuple) -> _bridge.WarpOp:
    v3 = _bridge.vec_dtype(torch.empty(0, 3, dtype=dtype))
    v4 = _bridge.vec_dtype(torch.empty(0, 4, dtype=dtype))
    v2 = _bridge.vec_dtype(torch.empty(0, 2, dtype=dtype))
    sc = _bridge.float_dtype(torch.empty(0, dtype=dtype))
    consts = [sc(p) for p in params]

    def run(means, quats, scales, opacities, sign):
        n = means.shape[0]
        dev = means.device
        grad = _bridge.active_tape() is not None  # no tape: nothing differentiates this call
        points = _bridge.empty(n * samples, v3, dev, requires_grad=grad, zero=True)
        normals = _bridge.empty(n * samples, v3, dev, requires_grad=grad, zero=True)
        weights = _bridge.empty(n * samples, sc, dev, requires_grad=grad, zero=True)
        if n > 0:
            _bridge.launch(oriented_points_kernel, dim=n,
                      inputs=[means, quats, scales, opacities, sign, samples, *consts],
                      outputs=[points, normals, weights], device=dev)
        return points, normals, weights

    return _bridge.WarpOp("oriented_points", run, (v3, v4, v2, sc, sc), (True, True, True, True, False),
                          (True, True, True))


def oriented_points(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor, *,
                    samples: int = 5, offset: float = 0.5, opacity_threshold: float = 0.0, center_weight: float = 1.0,
                    offset_weight: float = 0.5, normal_sign: torch.Tensor | None = None) -> OrientedPoints:
    """Turn surfels into weighted oriented points: the centre plus 4 tangent-plane offsets.

    Sample ``k`` of surfel ``i`` is row ``i*S + k``: ``k = 0`` is the centre, ``k = 1..4`` are
    ``mean +- offset*scale[0]*x_axis`` and ``mean +- offset*scale[1]*y_axis`` (in that order), where
    ``x_axis, y_axis, z_axis`` are the columns of the rotation of ``quats``. All samples of a surfel
    share the normal ``z_axis * normal_sign[i]``. Weights are ``opacity * center_weight`` (centre) and
    ``opacity * offset_weight`` (offsets), and exactly 0 (with zero gradient) where
    ``opacity < opacity_threshold``.

    Quaternions may have any norm; they are normalised inside the kernel. A quaternion of norm
    below ``1e-7`` (in particular the zero quaternion) is treated as the identity rotation and gets
    a zero gradient. NaN/inf anywhere raises :class:`ValueError`.

    Args:
        means: surfel centres, shape ``[N, 3]``, float32 or float64 (scene units).
        quats: rotations as ``(w, x, y, z)`` quaternions of any norm, shape ``[N, 4]``.
        scales: linear tangent-axis scales, shape ``[N, 2]`` (scene units).
        opacities: opacities in ``[0, 1]``, shape ``[N]``.
        samples: 1 (centres only) or 5.
        offset: offset along each tangent axis in units of that axis' scale.
        opacity_threshold: surfels with opacity below this get weight 0.
        center_weight: weight factor of the centre sample.
        offset_weight: weight factor of each offset sample.
        normal_sign: optional ``[N]`` tensor of +-1 flipping each surfel's normal (not differentiable).

    Returns:
        :class:`OrientedPoints` with ``points [N*S, 3]``, unit ``normals [N*S, 3]``, ``weights [N*S]``,
        all of the dtype of ``means``. Differentiable w.r.t. ``means``, ``quats``, ``scales`` and
        ``opacities``.
    """
    require_tensor("means", means, shape=(None, 3))
    n = means.shape[0]
    dtype = means.dtype
    require_tensor("quats", quats, shape=(n, 4), dtypes=(dtype,))
    require_tensor("scales", scales, shape=(n, 2), dtypes=(dtype,))
    require_tensor("opacities", opacities, shape=(n,), dtypes=(dtype,))
    if normal_sign is not None:
        require_tensor("normal_sign", normal_sign, shape=(n,), dtypes=None)
    require_same_device(means=means, quats=quats, scales=scales, opacities=opacities, normal_sign=normal_sign)
    if samples not in (1, 5):
        raise ValueError(f"samples must be 1 or 5, got {samples!r}")
    for name, value in (("offset", offset), ("center_weight", center_weight), ("offset_weight", offset_weight)):
        require_positive(name, value, allow_zero=True)
    require_positive("opacity_threshold", opacity_threshold, allow_zero=True)
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities)):
        require_finite(name, t.detach())
    if normal_sign is None:
        sign = torch.ones(n, dtype=dtype, device=means.device)
    else:
        sign = normal_sign.detach().to(dtype)
        bad = (sign.abs() != 1).nonzero() if value_checks() else None
        if bad is not None and bad.numel():  # host sync: validation only
            i = int(bad[0])
            raise ValueError(f"normal_sign must hold +-1, got {normal_sign[i].item()} at index {i}")
    if n == 0:
        # No launch on empty inputs (Warp cannot view zero-size tensors); keep the inputs in the
        # graph so backward gives zero-size gradients of the right shape.
        zero = means.sum() * 0 + quats.sum() * 0 + scales.sum() * 0 + opacities.sum() * 0
        return OrientedPoints(zero + means.new_zeros(0, 3), zero + means.new_zeros(0, 3), zero + means.new_zeros(0))
    params = (offset, opacity_threshold, center_weight, offset_weight, QUAT_EPS)
    pts, nrm, w = _bridge.apply(_op(dtype, samples, params), means, quats, scales, opacities, sign)
    return OrientedPoints(pts.view(n * samples, 3), nrm.view(n * samples, 3), w.view(n * samples))
