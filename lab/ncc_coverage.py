# SPDX-License-Identifier: Apache-2.0
"""Does the multi-view NCC term's coverage move the surfels onto the surface (#59, lab/depth_bias.py)?

    .venv/bin/python lab/ncc_coverage.py OUT FRACTION PIXELS [SCENE] [--set key=value ...]

PGSR draws 102,400 reference pixels a view for its multi-view term; wtopo draws 1/16 of the view, at most 4,096
(``wtopo.fitting.objective._MULTIVIEW_FRACTION``, ``_MULTIVIEW_PIXELS``). This fits SCENE (default bunny) on the
CPU with those two replaced and no polish (the surfels are the final fusion's), writes the run to OUT, then prints
lab/depth_bias.py's rendered-depth offsets. Nothing imports it.
"""

import os
import sys

from wtopo.fitting import objective

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import depth_bias  # noqa: E402


def main(argv: list[str]) -> None:
    out, fraction, pixels = argv[0], float(argv[1]), int(argv[2])
    objective._MULTIVIEW_FRACTION, objective._MULTIVIEW_PIXELS = fraction, pixels
    name, r = depth_bias.fit_without_polish(out, argv[3:])
    print(f"{name}, multi-view pixels 1/{1 / fraction:g} of a view, at most {pixels}: Chamfer "
          f"{r.get('chamfer')} F {r.get('f_score')}")
    depth_bias.main(out, name)


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    main(sys.argv[1:])
