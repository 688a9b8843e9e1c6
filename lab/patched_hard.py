# SPDX-License-Identifier: Apache-2.0
"""lab/hard.py with lab/fit_patches.py's patches installed first (one fit at a time: ``--jobs`` processes would not
see them).

    MASK_BAND=1 .venv/bin/python lab/patched_hard.py --variants default --label band1 --seeds 0
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import fit_patches  # noqa: E402
import hard  # noqa: E402

if __name__ == "__main__":
    if not fit_patches.install_from_env():
        sys.exit("no patch asked for: set one of lab/fit_patches.py's variables, or run lab/hard.py itself")
    sys.exit(hard.main(sys.argv[1:]))
