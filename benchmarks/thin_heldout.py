# SPDX-License-Identifier: Apache-2.0
"""A held-out thin-part scene for the hard suite's rules (``benchmarks/hard.md``, ``cpu_thin_decay``): a table
(top 1.0 x 0.64 x 0.06, four legs 0.05 square, two stretchers 0.04), never used to tune anything, fitted at the
CPU default and scored as the suite scores its scenes.

    PYTHONPATH=. .venv/bin/python benchmarks/thin_heldout.py SEED on|off|noloop OUT_JSON

``on``: ``optim.means_thin_decay=0.5``; ``off``: 0 (the fit's own decay); ``noloop``: no mesh loop. The fit
goes to ``runs/abl/table_<mode>_s<seed>``; the truth mesh is kept in ``.hardcache``."""
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard  # noqa: E402
import hard_scenes as hs  # noqa: E402

from wtopo import scenes  # noqa: E402
from wtopo.fitting import fit  # noqa: E402


def table_sdf(p):
    parts = [hs._box(p, (0, 0, 0.72), (0.5, 0.32, 0.03))]  # top
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(hs._box(p, (0.44 * sx, 0.26 * sy, 0.35), (0.025, 0.025, 0.35)))  # legs
        parts.append(hs._box(p, (0.44 * sx, 0.0, 0.18), (0.02, 0.26, 0.02)))  # stretchers: two more loops
    return np.min(parts, axis=0)


def main() -> None:
    """Fit the table once (``SEED MODE OUT_JSON``) and write its row."""
    seed, mode, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    hs.MESH_CACHE[:] = [".hardcache"]
    gt = hs.sdf_mesh(table_sdf, (-0.56, -0.38, -0.03), (0.56, 0.38, 0.78), 0.006)
    scene = scenes.from_mesh(gt, n_views=32, resolution=128, rig="sphere", texture="coffee", background="black",
                             seed=7, up=(0, 0, 1), n_test=hs.N_TEST, name="table")
    sets = [f"runtime.seed={seed}"] + {"on": ["optim.means_thin_decay=0.5"],
                                        "off": ["optim.means_thin_decay=0"],
                                        "noloop": ["coevolution.enabled=false"]}[mode]
    cfg = hard._config("default", sets)
    t = time.perf_counter()
    res = fit(scene, cfg, out_dir=f"runs/abl/table_{mode}_s{seed}", progress=False)
    row = {"scene": "table", "mode": mode, "seed": seed, "time": time.perf_counter() - t,
           **hard.measure(res.mesh, gt, cameras=hard._train_cameras(scene)), "psnr": res.report.get("psnr"),
           "coevolution": res.report.get("coevolution")}
    with open(out, "w") as f:
        json.dump(row, f, indent=1, default=str)
    print(f"table {mode} s{seed}: Chamfer {row['chamfer']:.3f} F {row['f_score']:.3f} holes {row['hole_frac']:.2f} "
          f"inward {row['inward']:+.3f} time {row['time']:.0f} thin {row['coevolution']}")


if __name__ == "__main__":
    main()
