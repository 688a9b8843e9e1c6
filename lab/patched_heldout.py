# SPDX-License-Identifier: Apache-2.0
"""lab/heldout.py with lab/fit_patches.py's patches installed first.

The held-out check of a candidate set on the hard suite; give each patched run its own ``--tag``:

    FUSION_DECAY=2 DECAY_THIN_ONLY=1 .venv/bin/python lab/patched_heldout.py --scene table 0 default OUT --tag thindecay
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import fit_patches  # noqa: E402
import heldout  # noqa: E402

if __name__ == "__main__":
    if not fit_patches.install_from_env():
        sys.exit("no patch asked for: set one of lab/fit_patches.py's variables, or run lab/heldout.py itself")
    heldout.main(sys.argv[1:])
