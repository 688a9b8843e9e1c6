# SPDX-License-Identifier: Apache-2.0
"""The mask term in the warm-up only (#59: wtopo's meshes lie inside the surface; design/decisions.md).

    .venv/bin/python lab/mask_warmup_only.py OUT [SCENE] [--set key=value ...]

Without its mask term the CPU bunny's mesh no longer lies inside the surface, but a short warm-up without it ends too
transparent for the TSDF re-initialisation. PGSR has no mask term. This keeps the term through the warm-up and drops
it from the co-evolution on (``Objective.__call__`` patched here), fits SCENE (default bunny) on the CPU without the
polish, writes the run to OUT and prints lab/depth_bias.py's offsets. ``install()`` is lab/fit_patches.py's
MASK_WARMUP_ONLY (the hard suite: lab/patched_hard.py).
"""

import os
import sys

from wtopo.fitting import objective

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import depth_bias  # noqa: E402

_call = objective.Objective.__call__


def _warmup_mask_only(self, stage, it, vi, surfels, proxy, **kw):
    keep = self.mask_weight
    if stage != objective.Stage.WARMUP:
        self.mask_weight = 0.0
    try:
        return _call(self, stage, it, vi, surfels, proxy, **kw)
    finally:
        self.mask_weight = keep


def install() -> None:
    """Keep the mask term through the warm-up only, in every fit of this process."""
    objective.Objective.__call__ = _warmup_mask_only


def main(argv: list[str]) -> None:
    install()
    name, r = depth_bias.fit_without_polish(argv[0], argv[1:])
    print(f"{name}, the mask term in the warm-up only: Chamfer {r.get('chamfer')} F {r.get('f_score')}")
    depth_bias.main(argv[0], name)


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
