# SPDX-License-Identifier: Apache-2.0
"""The photometric and mask terms both blind to a ring just outside the mask (#59: wtopo's meshes lie inside the
surface, design/decisions.md).

    RING_BLIND=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]      (RING_BLIND: the ring's width [px])
    RING_TERMS=photo (or mask): only that term is blind to the ring
    RING_MASK_TARGET=0.5: the mask term's target in the ring is that opacity (the photometric term stays blind)

lab/mask_band.py made only the mask term blind to the ring; the blob's offset did not move, and the photometric term
still sees the low-pass's halo against the black background there. Here, in the RING_BLIND pixels outside the mask
nearest it (a square dilation), the rendered colour is replaced by the photograph's and the rendered opacity by the
mask's before any term reads them, so neither the photometric term (L1 and SSIM) nor the mask term pulls on them.
``install()`` patches ``wtopo.fitting.pixel_terms._inputs`` (lab/fit_patches.py's RING_BLIND). The photometric half
is the product's since lab/hard.md "ringphoto" (``wtopo.fitting.pixel_terms.halo_ring``), so on today's tree
RING_TERMS=photo changes nothing and RING_BLIND=1 adds the mask term's blindness.
"""

import os

import torch
import torch.nn.functional as F

from wtopo.fitting import pixel_terms

BAND = int(os.environ.get("RING_BLIND", "1"))
TERMS = os.environ.get("RING_TERMS", "photo,mask").split(",")  # which terms are blind: photo, mask or both
SOFT = os.environ.get("RING_MASK_TARGET")  # the mask term's target opacity in the ring, in place of blindness
_inputs = pixel_terms._inputs


def ring(mask: torch.Tensor) -> torch.Tensor:
    """The pixels outside ``mask`` [H, W] within BAND pixels of it (square dilation), bool [H, W]."""
    inside = (mask.float() >= 0.5)[None, None].float()
    grown = F.max_pool2d(inside, 2 * BAND + 1, stride=1, padding=BAND)[0, 0]
    return (grown - inside[0, 0]) > 0.5


def blind_inputs(ts, render, image, mask, rays, windows):
    """``_inputs`` with the ring's colour and opacity set to their targets (no gradient there)."""
    args = list(_inputs(ts, render, image, mask, rays, windows))
    if mask is None or ts.mask <= 0:
        return tuple(args)
    r = ring(mask)
    if "photo" in TERMS:
        args[0] = torch.where(r[..., None], image.to(args[0].dtype), args[0])
    if SOFT is not None:
        k = next(i for i, a in enumerate(args) if a is image) + 1  # the mask follows the photograph
        args[k] = torch.where(r, torch.full_like(args[k], float(SOFT)), args[k])
    elif "mask" in TERMS:
        args[1] = torch.where(r, mask.to(args[1].dtype), args[1])
    return tuple(args)


def install() -> None:
    """Use :func:`blind_inputs` in every fit of this process."""
    pixel_terms._inputs = blind_inputs
