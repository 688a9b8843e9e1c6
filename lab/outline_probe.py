# SPDX-License-Identifier: Apache-2.0
"""What a mesh's silhouettes miss of the training masks, and how (#59: the outline offset moves the chairs outward
although their surfaces already lie outside the truth). Nothing imports it.

    PYTHONPATH=. .venv/bin/python lab/outline_probe.py EXCH MESH [MESH ...]

EXCH: an exchange folder of benchmarks/peers/export.py (its training cameras and masks); MESH: a mesh in that
scene's frame. Per mesh: the median of the product's per-view measure (``outline_offset``, wtopo/geometry/outline.py:
(mask area - silhouette area) / outline length) and, over the training views whose mask stays inside the frame, the
pixels the
silhouette misses inside the masks and spills outside them, and the share of the missed pixels deeper than 1.5 px
inside a missed region (a part the mesh lacks, rather than an outline drawn in by a fraction of a pixel).
"""

import os
import sys

import numpy as np
import torch
import trimesh
from scipy import ndimage

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "peers"))
import exchange  # noqa: E402

from wtopo.geometry.outline import outline_offset  # noqa: E402
from wtopo.raycast import MeshRaycaster  # noqa: E402


def probe(ex, path: str) -> str:
    cams = [ex.camera(i) for i in ex.train]
    masks = [ex.mask(i) >= 0.5 for i in ex.train]
    m = trimesh.load(path, process=False)
    v = torch.as_tensor(np.asarray(m.vertices), dtype=torch.float32)
    f = torch.as_tensor(np.asarray(m.faces), dtype=torch.int32)
    caster = MeshRaycaster()  # one BVH for the product's measure and the pixel counts
    off = outline_offset(v, f, cams, masks, raycaster=caster)
    missed, deep, spilled = 0, 0, 0
    for cam, mk in zip(cams, masks):
        if mk[0].any() or mk[-1].any() or mk[:, 0].any() or mk[:, -1].any():
            continue
        hit = caster.raycast(v, f, cam).mask.cpu().numpy().astype(bool)
        miss = mk & ~hit
        missed += int(miss.sum())
        spilled += int((hit & ~mk).sum())
        deep += int((ndimage.distance_transform_edt(miss) > 1.5).sum())
    return (f"{path}: per-view offset median {off.median_pixels:+.3f} px over {len(off.views)} views | missed "
            f"{missed} px ({100 * deep / max(missed, 1):.0f} % deeper than 1.5 px), spilled {spilled} px")


if __name__ == "__main__":
    ex = exchange.load(sys.argv[1])
    for p in sys.argv[2:]:
        print(probe(ex, p), flush=True)
