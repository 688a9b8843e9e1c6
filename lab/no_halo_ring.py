# SPDX-License-Identifier: Apache-2.0
"""The fit without the photometric term's halo ring (#59): what the product did before ``pixel_terms.halo_ring``, for
a paired check at another seed.

    NO_HALO_RING=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]

``install()`` makes ``halo_ring`` (the pixel terms' and the objective's) return no pixel
(lab/fit_patches.py's NO_HALO_RING).
"""

import torch

from wtopo.fitting import objective, pixel_terms


def install() -> None:
    """An empty ring in every fit of this process (the objective keeps its own name of ``halo_ring``)."""
    def no_ring(mask, width=pixel_terms.HALO_RING):
        return torch.zeros(mask.shape, dtype=torch.bool, device=mask.device)

    pixel_terms.halo_ring = objective.halo_ring = no_ring
