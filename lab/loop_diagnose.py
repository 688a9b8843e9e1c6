# SPDX-License-Identifier: Apache-2.0
"""Why the proxy-mesh loop helps or hurts a scene of the hard suite (issue 15): per-iteration traces
of one fit with the ground truth in hand.

Every ``--every`` co-evolution iterations (and at its start) it records, in % of the truth's
bounding-box diagonal (the region of interest's truth for ``chair_ground``):

* ``surf``: mean distance of the opaque (>= 0.5) surfels inside the region to the truth;
* ``proxy_acc`` / ``proxy_compl``: the proxy mesh (built from the current surfels) to the truth and
  back, its part inside the region only;
* ``proxy_far``: % of the proxy's area inside the region farther than tau (0.5 %) from the truth;
* ``unsupported``: % of the proxy's area inside the region farther than tau from every opaque surfel;
* per loss term (``photo``, ``mesh_depth``, ``mesh_normal``): the norm of its gradient w.r.t. the
  surfel means, and ``toward``: the share of that gradient's descent direction (summed over surfels,
  weighted by magnitude) that points towards the truth (nearest truth point) rather than away;
* ``bad_px``: % of the pixels the mesh-depth term uses where the proxy's depth is farther than tau
  from the truth's depth while the surfels' is not (the term pulls good surfels to a wrong proxy).

and ``helpful_px`` the reverse. The final mesh is scored as ``lab/hard.py`` scores it.

Command (``--resume-from`` starts at a suite run's warm-up checkpoint, so the variants share the warm-up;
``--set coevolution.enabled=true`` forces the loop on for a scene, where the plan leaves it out)::

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 10 python lab/loop_diagnose.py --scene chair_ground \
        --every 20 --out /tmp/diag_loop.json --set coevolution.enabled=true \
        [--resume-from /tmp/wtopo_hard/<label>/chair_ground_default/checkpoints/ckpt_00000400.pt]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hard  # noqa: E402
from wtopo.fitting.loop import FitRun  # noqa: E402
from wtopo.fitting.stages import Stage  # noqa: E402

_SAMPLES = 60_000  # area samples of the truth and the proxy for the distances


def _inside(p, lo, hi):
    return np.all((p >= lo) & (p <= hi), axis=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="chair_ground", choices=list(hard.SCENES))
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--every", type=int, default=20)
    ap.add_argument("--out", required=True)
    ap.add_argument("--resume-from", help="a warm-up checkpoint (ckpt_*.pt of a suite run of this scene, e.g. "
                    "/tmp/wtopo_hard/<label>/chair_ground_default/checkpoints/ckpt_00000400.pt): start there")
    ap.add_argument("--run-dir", default="/tmp/wtopo_diag")
    args = ap.parse_args(argv)
    scene, gt = hard.SCENES[args.scene]()
    box = tuple(np.asarray(b, np.float64) for b in scene.info["roi"]) if "roi" in scene.info else None
    gt = gt if gt is not None else scene.gt_mesh
    cfg = hard._config("default", args.set)
    cfg.runtime.eval_every = 0
    cfg.runtime.checkpoint_every = 0
    out_dir = None
    if args.resume_from:  # the warm-up is the same for every variant: start from its checkpoint
        import shutil

        out_dir = os.path.join(args.run_dir, os.path.splitext(os.path.basename(args.out))[0])
        shutil.rmtree(out_dir, ignore_errors=True)
        os.makedirs(os.path.join(out_dir, "checkpoints"))
        shutil.copy(args.resume_from, os.path.join(out_dir, "checkpoints"))
    run = FitRun(scene, cfg, out_dir, progress=False)
    if args.resume_from:
        run.hash = torch.load(args.resume_from, weights_only=False)["config_hash"]  # the variant's own config runs
    sim = run.sim
    gti = sim.to_internal(gt)
    diag = float(np.linalg.norm(gti.bounds[1] - gti.bounds[0]))
    tau = hard.TAU_FRACTION * diag
    gt_pts, _ = trimesh.sample.sample_surface(gti, _SAMPLES, seed=0)
    gt_tree = cKDTree(gt_pts)
    if box is not None:
        lo, hi = (np.asarray(sim.to_internal(b[None]))[0] for b in box)
    else:
        lo, hi = gti.bounds[0] - 0.05 * diag, gti.bounds[1] + 0.05 * diag
    pct = 100.0 / diag
    trace: list[dict] = []

    def measure_state(it: int, stage: str) -> dict:
        s = run.surfels
        m = s.means.detach().cpu().numpy()
        op = s.opacities.detach().cpu().numpy().reshape(-1)
        sel = (op >= 0.5) & _inside(m, lo, hi)
        d, _ = gt_tree.query(m[sel])
        rec = {"it": it, "stage": stage, "surfels": int(len(m)), "surf": float(d.mean() * pct),
               "surf_far": float(100 * (d > tau).mean())}
        with torch.no_grad():
            pm = run.proxy.build(s)
        if pm is not None:
            pmesh = trimesh.Trimesh(pm.verts.cpu().numpy(), pm.faces.cpu().numpy(), process=False)
            pts, _ = trimesh.sample.sample_surface(pmesh, _SAMPLES, seed=0)
            pts = pts[_inside(pts, lo, hi)]
            da, _ = gt_tree.query(pts)
            dc, _ = cKDTree(pts).query(gt_pts)
            ds, _ = cKDTree(m[op >= 0.5]).query(pts)
            rec.update(faces=int(pm.faces.shape[0]), proxy_acc=float(da.mean() * pct),
                       proxy_compl=float(dc.mean() * pct),
                       proxy_far=float(100 * (da > tau).mean()), unsupported=float(100 * (ds > tau).mean()),
                       proxy_area_in_roi=float(pmesh.area * len(pts) / _SAMPLES))
        return rec

    obj_call = run.objective.__call__

    def objective(stage, it, vi, surfels, proxy, **kw):
        t = obj_call(stage, it, vi, surfels, proxy, **kw)
        if stage == Stage.COEVOLUTION and (it - run.warmup_end) % args.every == 0:
            rec = measure_state(it, stage.value)
            means = surfels.params["means"]
            m = means.detach().cpu().numpy()
            _, idx = gt_tree.query(m)
            to_gt = torch.as_tensor(gt_pts[idx] - m, dtype=torch.float32)
            for k in ("photo", "mesh_depth", "mesh_normal", "normal", "distortion"):
                if k not in t.losses or not t.losses[k].requires_grad:
                    continue
                (g,) = torch.autograd.grad(t.losses[k], means, retain_graph=True, allow_unused=True)
                if g is None:
                    continue
                g = g.detach().cpu()
                gn = g.norm(dim=1)
                cos = -(g * to_gt).sum(1) / (gn * to_gt.norm(dim=1)).clamp_min(1e-20)
                w = gn / gn.sum().clamp_min(1e-30)
                rec[f"g_{k}"] = float(gn.sum())
                rec[f"toward_{k}"] = float((w * (cos > 0).float()).sum() * 100)
            if t.proxy is not None and "mesh_depth" in t.losses:
                cam = run.train.cameras[vi]
                mr = proxy.render(t.proxy, cam)
                both = (mr.mask & t.covered).cpu().numpy()
                gtd = run.train.depths[vi].cpu().numpy()
                sd = t.render.median_depth.detach().cpu().numpy()
                md = mr.depth.detach().cpu().numpy()
                ok = both & (gtd > 0)
                bad = ok & (np.abs(md - gtd) > tau) & (np.abs(sd - gtd) <= tau)
                good = ok & (np.abs(md - gtd) <= tau) & (np.abs(sd - gtd) > tau)
                rec["bad_px"] = float(100 * bad.sum() / max(1, ok.sum()))
                rec["helpful_px"] = float(100 * good.sum() / max(1, ok.sum()))
                rec["depth_err_surf"] = float(np.abs(sd - gtd)[ok].mean() * pct)
                rec["depth_err_proxy"] = float(np.abs(md - gtd)[ok].mean() * pct)
            rec.update({k: float(v.detach()) for k, v in t.losses.items()})
            trace.append(rec)
            print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rec.items()}), flush=True)
        return t

    run.objective = objective
    mesh = run.run()
    world = sim.to_world(mesh)
    if box is not None:
        world = hard.clip_to_box(world, *box)
    final = hard.measure(world, gt)
    print("final", json.dumps({k: final[k] for k in ("chamfer", "f_score", "accuracy", "completeness",
                                                      "floater_frac", "hole_frac")}), flush=True)
    with open(args.out, "w") as f:
        json.dump({"trace": trace, "final": final, "sets": args.set}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
