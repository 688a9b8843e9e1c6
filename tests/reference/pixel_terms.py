# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference of :func:`wtopo.pixel_terms.pixel_terms` (the formulation the fused pass replaced): the
depth normals of :mod:`reference.depth_normals`, then each term as torch operations."""

from __future__ import annotations

import torch.nn.functional as F
from reference.depth_normals import depth_normals_torch

__all__ = ["pixel_terms_torch"]


def pixel_terms_torch(normal, alpha, median_depth, distortion, origins, directions, valid, target=None, *,
                      eps=1e-8, clamp=1e-6):
    """``(normal, distortion, mask or None)`` as :func:`wtopo.pixel_terms.pixel_terms` documents them."""
    dn, dm = depth_normals_torch(median_depth.detach(), origins, directions, valid, eps)
    m = dm.to(alpha.dtype)
    dot = (normal * dn).sum(-1)
    normal_term = ((alpha.detach() - dot) * m).sum() / m.sum().clamp_min(1.0)
    mask_term = None
    if target is not None:
        a = alpha.clamp(clamp, 1.0 - clamp)
        mask_term = F.binary_cross_entropy(a, target.to(alpha.dtype))
    return normal_term, distortion.mean(), mask_term
