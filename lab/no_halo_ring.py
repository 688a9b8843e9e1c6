# SPDX-License-Identifier: Apache-2.0
"""The fit without the photometric term's halo ring (#59): what the product did before ``pixel_terms.halo_ring``, for
a paired check at another seed.

    NO_HALO_RING=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]

``install()`` makes ``wtopo.fitting.pixel_terms.halo_ring`` return no pixel (lab/fit_patches.py's NO_HALO_RING).
"""

import torch

from wtopo.fitting import pixel_terms


def install() -> None:
    """An empty ring in every fit of this process."""
    pixel_terms.halo_ring = lambda mask, width=pixel_terms.HALO_RING: torch.zeros(mask.shape, dtype=torch.bool,
                                                                                  device=mask.device)
