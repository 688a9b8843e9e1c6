# SPDX-License-Identifier: Apache-2.0
"""The lab's patches of a fit, chosen by environment variables: one place for lab/patched_hard.py (the CPU hard
suite) and lab/device/patched_run.py (the peers harness's fits on a GPU). Each patch's module says what it changes
and what it measured.

    MASK_WARMUP_ONLY=1    the mask term through the warm-up only (lab/mask_warmup_only.py)
    MASK_BAND=N           the mask term blind to an N-px ring outside the mask (lab/mask_band.py)
    FINAL_TRUNCATION=V    the final fusion truncated at V voxels, not 4 (lab/final_truncation.py)
    FUSION_DECAY=V        fusion weights fading out from V voxels behind a view's depth (lab/fusion_decay.py)
    RING_BLIND=N          the photometric and mask terms blind to an N-px ring outside the mask (lab/ring_blind.py)

Only in-process fits see a patch: lab/hard.py's ``--jobs`` processes would not. Nothing in the product imports it.
"""

import os


def install_from_env() -> list[str]:
    """Install every patch its variable asks for; returns the variables that were set."""
    used = []
    if os.environ.get("MASK_WARMUP_ONLY"):
        import mask_warmup_only

        mask_warmup_only.install()
        used.append("MASK_WARMUP_ONLY")
    if os.environ.get("MASK_BAND"):
        import mask_band

        mask_band.install()
        used.append("MASK_BAND")
    if os.environ.get("FINAL_TRUNCATION"):
        import final_truncation

        final_truncation.install()
        used.append("FINAL_TRUNCATION")
    if os.environ.get("FUSION_DECAY"):
        import fusion_decay

        fusion_decay.install()
        used.append("FUSION_DECAY")
    if os.environ.get("RING_BLIND"):
        import ring_blind

        ring_blind.install()
        used.append("RING_BLIND")
    return used
