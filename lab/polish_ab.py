"""Lab (nothing imports it; it decided ``FitConfig.polish``, when the polish came after the final mesh; since
9e43398 the mesh is fused after the polish): does a photometric polish after the loop give back the held-out
PSNR that the mesh loop costs (#59: on the 64-view chair the loop costs 0.23 dB and wtopo trails gsplat by 0.48)?
One fit at the default with the product's polish off; its final mesh and held-out PSNR; then the same surfels
trained on for ``--polish`` more iterations with the mesh terms and the geometry-aware density control off (the
means' rate at its final value), the held-out PSNR after each step of ``--polish`` (``--keep-mesh``: the control,
the co-evolution going on). Prints JSON lines.

    PYTHONPATH=. .venv/bin/python lab/polish_ab.py [--scene bunny] [--seed 0] [--polish 100 200] [--keep-mesh]
"""
import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="bunny")
    ap.add_argument("--views", type=int, default=48, help="a peers' scene: views (0: the harness's)")
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--polish", type=int, nargs="+", default=[100, 200], help="cumulative polish iterations")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--product", action="store_true", help="the default fit with the plan's own polish: held-out "
                    "PSNR at the co-evolution's end and after the polish, and the seconds from the one to the fit's "
                    "end (the polish and the final mesh)")
    ap.add_argument("--share", type=float, default=None, help="with --product: polish this share of the plan's "
                    "co-evolution whatever the plan says (a scene, whose plan has no polish)")
    ap.add_argument("--photo-only", action="store_true", help="the polish without the normal, distortion and "
                    "multi-view terms (photometric, mask and scale terms only)")
    ap.add_argument("--keep-mesh", action="store_true", help="the control: the polish keeps the mesh terms and the "
                    "density control (the co-evolution goes on)")
    a = ap.parse_args()

    import scenes as peer_scenes

    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig
    from wtopo.fitting.loop import FitRun
    from wtopo.fitting.stages import Stage

    if a.scene not in peer_scenes.names():
        scene = wtopo.scenes.load(a.scene)
    elif a.views > 0:
        scene = peer_scenes.load(a.scene, n_views=a.views, resolution=a.size)
    else:
        scene = peer_scenes.load(a.scene)
    cfg = FitConfig()
    # the product's own polish off: this script's polish (or its control) follows the fit
    own = [] if a.product else ["polish.iterations=0"]
    for item in ["runtime.device=cpu", "runtime.usd_every=0", f"runtime.seed={a.seed}", *own, *a.set]:
        _apply_set(cfg, item)
    if a.product:
        if a.share is not None:
            import torch

            from wtopo.fitting.plan import make_plan

            coevo = make_plan(scene.normalized(), cfg, torch.device("cpu")).coevolution_iterations
            cfg.polish.iterations = round(a.share * coevo)
        res = wtopo.fit(scene, cfg, progress=False)
        end = [r for r in res.history if r["stage"] == "coevolution"][-1]  # the loop's last record
        last = res.history[-1]
        print(json.dumps({"scene": a.scene, "seed": a.seed, "polish": res.plan.polish_iterations,
                          "iterations": res.report["iterations"], "psnr_loop_end": end.get("psnr"),
                          "psnr": last.get("psnr"), "polish_and_mesh_s": round(last["elapsed"] - end["elapsed"], 1),
                          "fit_s": res.report["elapsed_s"], "chamfer": res.report.get("chamfer")}), flush=True)
        return
    t0 = time.perf_counter()
    run = FitRun(scene, cfg, None, progress=False)
    run.run()
    rec = run.history[-1]
    keys = ("psnr", "ssim", "chamfer", "f_score")
    print(json.dumps({"scene": a.scene, "seed": a.seed, "polish": 0, "s": round(time.perf_counter() - t0, 1),
                      **{k: rec.get(k) for k in keys}}), flush=True)
    if a.photo_only:
        run.cfg.losses.normal = run.cfg.losses.distortion = run.cfg.losses.multiview = 0.0
        run.objective.multiview = None
    if not a.keep_mesh:
        run.objective.mesh_terms = False
        run.cfg.densify.geometry_prune = False
        run.cfg.densify.geometry_densify = False
    total = run.it
    for n in a.polish:
        t1 = time.perf_counter()
        run._iterate(Stage.COEVOLUTION, run.it, total + n)
        r = run._evaluate(Stage.FINAL)
        print(json.dumps({"scene": a.scene, "seed": a.seed, "polish": n, "keep_mesh": a.keep_mesh,
                          "photo_only": a.photo_only,
                          "s": round(time.perf_counter() - t1, 1), **{k: r.get(k) for k in ("psnr", "ssim")},
                          "surfels": len(run.surfels)}), flush=True)


if __name__ == "__main__":
    main()
