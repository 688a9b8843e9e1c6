# SPDX-License-Identifier: Apache-2.0
"""The proxy mesh of a scene without masks, four ways on the same surfels (issue 15): one global zero level
or a local one (``mesh.level_sigma``), clipped to the region of interest or not (``mesh.clip_to_region``).

It loads a checkpoint of a hard-suite fit of ``--scene`` (default ``chair_ground``, the chair on its floor, no
masks; any checkpoint: the warm-up's end, or a co-evolution's), builds the four proxies on the grid that fit
used (an object, which has no region to clip to, gets the two levels only), and
scores each against the truth: accuracy and completeness of its part in the region (% of the truth's
diagonal), and over every training view's ray cast, on the pixels whose true surface lies in the region, the
median and mean depth error against the truth's depth where the proxy hits (what the mesh-depth term would pull
towards) and the share of those pixels it misses. The surfels' own rendered median depth is scored the same
way, as the bar the proxy must clear.

Command (a checkpoint of any suite run of the scene, kept with ``--set runtime.keep_checkpoints=50``; pass the
fit's own ``--set`` options so its configuration resumes)::

    PYTHONPATH=. .venv/bin/python lab/scene_proxy.py RUN/chair_ground_default/checkpoints/ckpt_00001681.pt
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import tempfile

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard  # noqa: E402
from wtopo.fitting.loop import FitRun  # noqa: E402
from wtopo.fitting.proxy import ProxyMesh  # noqa: E402

_SAMPLES = 60_000  # area samples of the truth and of each proxy


def _depth_errors(pairs, pct):
    """``(median %, mean %, missed %)`` of ``[(depth, hit mask, truth depth, truth pixels)]`` over the truth pixels."""
    err, missed, total = [], 0, 0
    for depth, hit, gtd, seen in pairs:
        both = seen & hit
        err.append(np.abs(depth - gtd)[both])
        missed += int((seen & ~hit).sum())
        total += int(seen.sum())
    e = np.concatenate(err)
    return float(np.median(e) * pct), float(e.mean() * pct), 100.0 * missed / max(1, total)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint", help="ckpt_<iteration>.pt of a hard-suite fit of --scene")
    ap.add_argument("--scene", default="chair_ground",
                    help="the suite scene the checkpoint is of; an object (no region) compares the two levels only")
    ap.add_argument("--level-sigma", type=float, default=2.0, help="the local level's Gaussian, cells")
    ap.add_argument("--set", action="append", default=[], help="the fit's own --set options, if any")
    ap.add_argument("--resolution", type=int, help="the proxy's grid (default: the one the fit used)")
    args = ap.parse_args(argv)
    scene, gt = hard.SCENES[args.scene]()
    gt = scene.gt_mesh if gt is None else gt  # an object's truth is its scene's own mesh
    cfg = hard._config("default", args.set)
    with tempfile.TemporaryDirectory() as tmp:  # FitRun resumes from a run directory's checkpoints/
        os.makedirs(os.path.join(tmp, "checkpoints"))
        shutil.copy(args.checkpoint, os.path.join(tmp, "checkpoints", os.path.basename(args.checkpoint)))
        run = FitRun(scene, cfg, tmp, progress=False)
        run.hash = torch.load(args.checkpoint, weights_only=False)["config_hash"]
        if not run.checkpoints.resume():
            raise SystemExit(f"{args.checkpoint}: not a checkpoint FitRun can resume")
    sim, s = run.sim, run.surfels
    gti = sim.to_internal(gt)
    roi = scene.info.get("roi")
    if roi is None:  # an object: the whole truth counts, nothing to clip to
        lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    else:
        lo, hi = (np.asarray(sim.to_internal(np.asarray(b)[None]))[0] for b in roi)
    diag = float(np.linalg.norm(gti.bounds[1] - gti.bounds[0]))
    pct = 100.0 / diag
    gt_pts, _ = trimesh.sample.sample_surface(gti, _SAMPLES, seed=0)
    tree = cKDTree(gt_pts)
    res = int(args.resolution or run.coevolution_info.get("resolution") or run.cfg.mesh.resolution)
    cams, depths = run.train.cameras, [d.numpy() for d in run.train.depths]
    in_roi = []  # the truth pixels whose surface point lies in the region of interest (the rest is background)
    for cam, gtd in zip(cams, depths):
        o, d = (t.numpy() for t in cam.pixel_rays("cpu", torch.float64))
        p = o + d * gtd[..., None]  # depth is the ray parameter (d_z = 1)
        in_roi.append((gtd > 0) & np.all((p >= lo) & (p <= hi), axis=-1))
    print(f"{args.checkpoint}: iteration {run.it}, {len(s)} surfels, proxy grid {res}^3; % of the truth's diagonal")
    with torch.no_grad():
        pairs = []
        for cam, gtd, seen in zip(cams, depths, in_roi):
            out = run.render(s, cam)
            pairs.append((out.median_depth.numpy(), (out.alpha >= 0.5).numpy(), gtd, seen))
    med, mean, miss = _depth_errors(pairs, pct)
    print(f"| surfels (rendered median depth) | | | {med:.3f} | {mean:.3f} | {miss:.1f} |")
    print("| proxy | faces | acc / compl in the region | median depth error | mean depth error | truth pixels missed |")
    ways = ((0.0, False), (args.level_sigma, False)) + (((0.0, True), (args.level_sigma, True)) if roi else ())
    for level, clip in ways:
        mc = dataclasses.replace(run.cfg.mesh, level_sigma=level, resolution=res)
        proxy = ProxyMesh(mc, clip=(lo, hi) if clip else None)
        with torch.no_grad():
            pm = proxy.build(s)
            pairs = []
            for cam, gtd, seen in zip(cams, depths, in_roi):
                mr = proxy.render(pm, cam)
                pairs.append((mr.depth.numpy(), mr.mask.numpy(), gtd, seen))
        mesh = trimesh.Trimesh(pm.verts.numpy(), pm.faces.numpy(), process=False)
        pts, _ = trimesh.sample.sample_surface(mesh, _SAMPLES, seed=0)
        pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
        acc = tree.query(pts)[0].mean() * pct
        compl = cKDTree(pts).query(gt_pts)[0].mean() * pct
        med, mean, miss = _depth_errors(pairs, pct)
        name = f"{'local level ' + format(level, 'g') if level else 'global level'}, {'clipped' if clip else 'whole'}"
        print(f"| {name} | {len(mesh.faces)} | {acc:.3f} / {compl:.3f} | {med:.3f} | {mean:.3f} | {miss:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
