# SPDX-License-Identifier: Apache-2.0
"""The final fusion's truncation in voxels (#59: wtopo's meshes lie inside the surface, design/decisions.md).

    FINAL_TRUNCATION=2 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]

The final TSDF fusion truncates at ``wtopo.fitting.stages.TRUNCATION_VOXELS`` (4) voxels. Fused from the true depth
maps at the CPU plan's grid, that thickens the thin chair (+0.046 % of the diagonal on the mean, mean unsigned
0.109 %; at 2 voxels -0.040 % and 0.068 %: inside by as much) and leaves the compact blob on the truth
(lab/silhouette_excess.py, design/decisions.md). ``install()`` sets FINAL_TRUNCATION voxels for the final fusion
only (the re-initialisation's keeps 4), patched into ``wtopo.fitting._final_mesh`` (lab/fit_patches.py's
FINAL_TRUNCATION). Rejected at the CPU default (lab/hard.md "trunc2"): the torus +38 %, the
mug +58 %.
"""

import os


def install() -> float:
    """Patch the final fusion's truncation to FINAL_TRUNCATION voxels (default 2); returns it."""
    from wtopo.fitting import _final_mesh

    value = float(os.environ.get("FINAL_TRUNCATION", "2"))
    _final_mesh.TRUNCATION_VOXELS = value
    return value
