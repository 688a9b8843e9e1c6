# SPDX-License-Identifier: Apache-2.0
"""The final TSDF voxel against the pixel footprint: one fit per scene, its final mesh at several grids.

The plan sets ``final.resolution`` so that a voxel is ``_FINAL_FOOTPRINTS`` (0.4) pixel footprints wide, within
the preset's range. This fits each scene once (CPU, the given preset) and rebuilds only the final mesh from the
same surfels at the plan's grid times each ``--factors`` (0.5: voxels twice as wide), printing one JSON row per
(scene, factor) with Chamfer / F-score (relative to the truth's diagonal), faces and the final mesh's seconds.

    OMP_NUM_THREADS=1 PYTHONPATH=. python lab/final_voxel.py [--scenes bunny ring_capsule ...] \
        [--factors 1 0.75 0.5] [--preset balanced] [--out rows.jsonl]
"""
import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

SCENES = ("bunny", "ring_capsule", "bunny_room", "bunny_env", "table", "vase", "pretzel")


def load(name: str):
    if name in ("table", "stool", "shelf", "vase", "pretzel"):
        import hard_scenes as hs
        from heldout import SCENES as HELD
        from wtopo import scenes
        sdf, lower, upper = HELD[name]
        gt = hs.sdf_mesh(sdf, lower, upper, 0.006)
        return scenes.from_mesh(gt, n_views=32, resolution=128, rig="sphere", texture="coffee", background="black",
                                seed=7, up=(0, 0, 1), n_test=hs.N_TEST, name=name)
    from benchmarks.error_vs_runtime import load_scene
    return load_scene(name)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--factors", nargs="*", type=float, default=[1.0, 0.75, 0.5])
    ap.add_argument("--preset", default="balanced")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    from wtopo.fitting import FitConfig, Preset
    from wtopo.fitting.loop import FitRun

    for name in a.scenes:
        scene = load(name)
        cfg = FitConfig()
        cfg.preset = Preset(a.preset)
        cfg.runtime.device = "cpu"
        cfg.runtime.eval_every = 0
        cfg.runtime.usd_every = 0
        run = FitRun(scene, cfg, None, progress=False)
        run.run()
        base = int(run.cfg.final.resolution)
        for f in a.factors:
            run.cfg.final.resolution = max(16, round(base * f))
            t = time.perf_counter()
            mesh = run._final_mesh()
            dt = time.perf_counter() - t
            rec = run.evaluator(run.surfels, mesh=mesh)
            row = {"scene": name, "factor": f, "resolution": run.cfg.final.resolution, "faces": len(mesh.faces),
                   "final_s": round(dt, 2), "watertight": bool(mesh.is_watertight),
                   **{k: rec.get(k) for k in ("chamfer", "f_score", "accuracy", "completeness", "psnr")},
                   "final_grid_thin": [e["resolution"] for e in run.events if e["event"] == "final_grid_thin"],
                   "thin": run.coevolution_info}
            print(json.dumps(row), flush=True)
            if a.out:
                with open(a.out, "a") as fh:
                    fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
