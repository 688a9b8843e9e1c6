# SPDX-License-Identifier: Apache-2.0
"""The mask term blind to a ring just outside the mask (#59: wtopo's meshes lie inside the surface, decisions.md).

    MASK_BAND=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]      (MASK_BAND: the ring's width [px])

Surfels placed exactly on the truth render a silhouette 0.7-1 px wider than the truth's at the CPU plan's 0.35-px
low-pass (lab/silhouette_excess.py): every edge-on surfel near the limb adds its low-pass disk, and a stack of
semi-transparent surfels saturates their sum. The mask term's binary cross-entropy then pulls the surface in until
the halo fits inside the mask. Here the term ignores the pixels outside the mask within MASK_BAND pixels of it
(a square dilation), so the halo costs nothing there while the inside still has to be covered and the farther
outside empty. ``install()`` patches ``wtopo.fitting.pixel_terms.mask_loss`` (lab/fit_patches.py's MASK_BAND).
"""

import os

import torch
import torch.nn.functional as F

from wtopo.fitting import pixel_terms

BAND = int(os.environ.get("MASK_BAND", "1"))


def banded_mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy over the pixels that are inside the mask or more than BAND pixels outside it."""
    m = mask.to(alpha.dtype)
    inside = (m >= 0.5).to(alpha.dtype)[None, None]
    grown = F.max_pool2d(inside, 2 * BAND + 1, stride=1, padding=BAND)[0, 0]
    weight = 1.0 - (grown - inside[0, 0])  # 0 on the ring, 1 elsewhere
    a = alpha.clamp(1e-6, 1 - 1e-6)
    return F.binary_cross_entropy(a, m, weight=weight, reduction="sum") / weight.sum().clamp_min(1.0)


def install() -> None:
    """Use :func:`banded_mask_loss` in every fit of this process."""
    pixel_terms.mask_loss = banded_mask_loss
