# SPDX-License-Identifier: Apache-2.0
"""The lab's patches of a fit, chosen by environment variables: one place for lab/patched_hard.py (the CPU hard
suite) and lab/device/patched_run.py (the peers harness's fits on a GPU). Each patch's module says what it changes
and what it measured.

    MASK_WARMUP_ONLY=1    the mask term through the warm-up only (lab/mask_warmup_only.py)
    MASK_BAND=N           the mask term blind to an N-px ring outside the mask (lab/mask_band.py)
    FINAL_TRUNCATION=V    the final fusion truncated at V voxels, not 4 (lab/final_truncation.py)
    FUSION_DECAY=V        fusion weights fading out from V voxels behind a view's depth (lab/fusion_decay.py)
    FUSION_MASKED=1       the TSDF stages fuse no rendered depth outside the view's mask (lab/fusion_masked.py)
    RING_BLIND=N          the photometric and mask terms blind to an N-px ring outside the mask (lab/ring_blind.py)
    NO_HALO_RING=1        the photometric term sees the ring again, as before halo_ring (lab/no_halo_ring.py)
    KEEP_PRE_OUTLINE=1    the final mesh before the outline offset kept beside the result (lab/pre_outline.py)
    SCENE_FUSION=K:T:F,.. the final fusion again at other grids, truncations, face tolerances (lab/scene_fusion.py)
    GEO_CONSISTENCY=W     PGSR's multi-view geometric consistency term at weight W (lab/geo_consistency.py)

Only in-process fits see a patch: lab/hard.py's ``--jobs`` processes would not. Nothing in the product imports it.
"""

import importlib
import os

# each variable and the lab module whose install() applies its patch, in the order they are installed
PATCHES = [("MASK_WARMUP_ONLY", "mask_warmup_only"), ("MASK_BAND", "mask_band"),
           ("FINAL_TRUNCATION", "final_truncation"), ("FUSION_DECAY", "fusion_decay"),
           ("FUSION_MASKED", "fusion_masked"), ("RING_BLIND", "ring_blind"), ("NO_HALO_RING", "no_halo_ring"),
           ("KEEP_PRE_OUTLINE", "pre_outline"),
           ("SCENE_FUSION", "scene_fusion"), ("GEO_CONSISTENCY", "geo_consistency")]


def install_from_env() -> list[str]:
    """Install every patch its variable asks for; returns the variables that were set."""
    used = []
    for var, module in PATCHES:
        if os.environ.get(var):
            importlib.import_module(module).install()
            used.append(var)
    return used
