"""Lab (nothing imports it): which part of the fit costs held-out PSNR on a masked object (#59: the 64-view chair
renders 2.8 dB below gsplat's 2DGS on the GPU; neither twice the steps nor more surfels closes it). One CPU fit per
variant on one scene of the peers' set (default: the chair, 48 views of 200 px), in sequence; a variant is a list
of ``--set`` items. Prints held-out PSNR (inside the masks), Chamfer, F-score, surfels and time as JSON lines.

    PYTHONPATH=. .venv/bin/python lab/appearance_ab.py [--scene chair] [--views 48] [--size 200] [--only NAME ...]

``--views 0``: the peers' scene at the harness's size; a name outside the peers' set is a built-in scene.
"""
import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

VARIANTS = {
    "default": [],
    "no_distortion": ["losses.distortion=0"],
    "no_normal": ["losses.normal=0"],
    "no_loop": ["coevolution.enabled=false"],
    "filter_2dgs": ["filter_sigma=0.71"],
    "no_scale": ["losses.scale=0"],
    "no_reinit": ["tsdf.enabled=false"],
    "filter_025": ["filter_sigma=0.25"],
    "filter_018": ["filter_sigma=0.18"],
    "lr_colour_3dgs": ["optim.sh_dc=0.0025"],
    "lr_3dgs": ["optim.sh_dc=0.0025", "optim.scales=0.005", "optim.quats=0.001"],
}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="chair")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="+", default=list(VARIANTS))
    a = ap.parse_args()

    import scenes as peer_scenes

    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig

    for name in a.only:
        if a.scene not in peer_scenes.names():  # a built-in scene at its own size (bunny, bunny_env)
            scene = wtopo.scenes.load(a.scene)
        elif a.views > 0:
            scene = peer_scenes.load(a.scene, n_views=a.views, resolution=a.size)
        else:  # the peers' scene as the harness exports it
            scene = peer_scenes.load(a.scene)
        cfg = FitConfig()
        for item in ["runtime.device=cpu", "runtime.usd_every=0", f"runtime.seed={a.seed}", *VARIANTS[name]]:
            _apply_set(cfg, item)
        res = wtopo.fit(scene, cfg, progress=False)
        rep = res.report
        chamfer = rep.get("chamfer")
        row = {"scene": a.scene, "variant": name, "seed": a.seed, "psnr": rep.get("psnr"),
               "psnr_on": rep.get("psnr_on"), "surfels": rep.get("surfels"), "elapsed_s": rep.get("elapsed_s"),
               "chamfer_pct": None if chamfer is None else 100 * chamfer, "f_score": rep.get("f_score"),
               "roi_f1": rep.get("roi_f1")}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
