# SPDX-License-Identifier: Apache-2.0
"""Camera poses from photos alone (issue 17): ``wtopo.loaders.run_sfm`` (pycolmap) on the 2-core CPU.

Two captures whose true cameras are known; the structure from motion never reads them:

* ``synthetic``: the bunny (astronaut albedo) in the textured room of ``wtopo.scenes`` (gravel
  floor, brick walls), 64 views of 256 px from the upper hemisphere, written as RGBA PNG (alpha =
  the bunny's silhouette, which COLMAP ignores and the fit takes as the mask). Then fits of the
  same images and masks at 64 px (``--fit-downscale``), 150 + 50 iterations (``--fit-iterations``;
  the test-sized configuration), every other registered view, each of ``--fit-seeds``, from each of
  ``--fit-variants``: the true cameras; the recovered ones (photos undistorted to pinhole cameras by
  ``load_photos``) moved into the true frame by the similarity between the camera centres (the
  controlled comparison of the test: same frame, same random draws); the recovered poses with the
  true intrinsics; and a fit in the model's own frame, as a user runs it, its mesh mapped into the
  true frame afterwards. Each mesh is scored by Chamfer against the bunny where the camera
  alignment puts it and after the Tanks-and-Temples refinement of that alignment by ICP against
  the bunny (``wtopo.metrics.refine_alignment``).
* ``dtu``: DTU scan24 (``../shared/data/dtu_scan24/image``, 49 views of 384 px; research data:
  read from there, never copied; the model is written to ``--work`` or a temporary folder). The
  given cameras (``cameras_sphere.npz``, read by the DTU loader, millimetres) are used only to score.
  ``--dtu-fit`` also fits DTU from the given cameras and from the recovered ones moved into DTU's
  frame (same photos, held-out split and region; ``--dtu-set`` shrinks the budget) and reports
  held-out PSNR / SSIM of each and the Chamfer distance between the two meshes, camera-aligned and
  refined.

Reported per capture: registered views, mean reprojection error (px), time per step (features,
matching, mapping) on ``--threads`` CPU threads, camera-centre RMS after a similarity alignment
(Umeyama; absolute and as a fraction of the camera extent, the diagonal of the true centres' box),
recovered focal length against the true one.

Commands (figures in benchmarks/sfm.md)::

    nice -n 10 .venv/bin/python benchmarks/sfm.py --threads 2 --skip-dtu
    nice -n 10 .venv/bin/python benchmarks/sfm.py --threads 2 --skip-synthetic --dtu-fit \
        --dtu-set warmup.iterations=150 --dtu-set coevolution.iterations=50 --dtu-set runtime.image_scale=0.5
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import tempfile
import time

import numpy as np
import torch
import trimesh

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
from _from_tests import load  # noqa: E402  (beside this script)

small_fit_config = load("fit_configs.py").small_fit_config  # the test-sized fit configuration

from wtopo import Camera, Scene, load_scene, ops, scenes  # noqa: E402
from wtopo.fitting import FitConfig, fit  # noqa: E402
from wtopo.fitting.evaluate import geometry_metrics  # noqa: E402
from wtopo.loaders import SfMOptions, load_photos  # noqa: E402
from wtopo.metrics import align_similarity, chamfer, refine_alignment  # noqa: E402

DTU = os.path.join(ROOT, "..", "shared", "data", "dtu_scan24")
DTU_VARIANTS = ("given", "recovered", "recovered_undistorted")
SYNTHETIC_VARIANTS = ("true", "recovered", "recovered_true_intrinsics", "recovered_sfm_frame")


def _centre_error(recovered, truth_by_name) -> dict:
    """Similarity from recovered to true camera centres and the residual figures."""
    names = [c.name for c in recovered.cameras]
    true = np.array([truth_by_name[n].center for n in names])
    al = align_similarity(np.array([c.center for c in recovered.cameras]), true)
    every = np.array([c.center for c in truth_by_name.values()])
    extent = float(np.linalg.norm(every.max(0) - every.min(0)))
    return {"alignment": al, "rms": al.rms, "max": float(al.residuals.max()), "extent": extent,
            "rms_fraction": al.rms / extent}


def _motion(al, mesh) -> float:
    """Mean distance a similarity moves the vertices of ``mesh`` (its units)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    return float(np.linalg.norm(al.apply(v) - v, axis=1).mean())


def _sfm_row(label: str, scene, err: dict, true_focal: float, unit: str) -> dict:
    s = scene.info["sfm"]
    row = {"capture": label, "registered": f"{len(s['registered'])} / {len(s['images'])}",
           "reprojection_px": round(s["reprojection_error"], 3), "points": s["points"],
           "seconds": s["seconds"], "matcher": s["matcher"],
           "centre_rms": f"{err['rms']:.4g} {unit}", "centre_rms_pct_extent": round(100 * err["rms_fraction"], 3),
           "centre_max": f"{err['max']:.4g} {unit}",
           "focal_px": [round(s["camera"]["params"][0], 2), round(true_focal, 2)],
           "dropped": s["dropped"]}
    print(json.dumps(row, indent=1), flush=True)
    return row


def _camera(like, K, world_to_camera, distortion):
    return Camera(K, world_to_camera, like.width, like.height, distortion, like.name)


def synthetic(threads: int, work: str, warmup: int, coevolution: int, downscale: int, seeds: list[int],
              variants: list[str]) -> dict:
    from PIL import Image

    room = scenes.load("bunny_room", n_views=64, resolution=256)
    gt = room.gt_mesh
    photos = os.path.join(work, "synthetic", "images")
    if not os.path.isdir(photos):  # --work: a rerun reuses the photos and the model
        sil = ops.raycast_mesh(torch.as_tensor(gt.vertices, dtype=torch.float32),
                               torch.as_tensor(gt.faces, dtype=torch.int32), room.cameras).mask.numpy()
        os.makedirs(photos)
        rgba = np.concatenate([np.asarray(room.images), sil[..., None].astype(np.float32)], axis=-1)
        for i, a in enumerate(rgba):
            Image.fromarray((np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)).save(os.path.join(photos, f"{i:03d}.png"))
    rec = load_photos(os.path.dirname(photos), options=SfMOptions(num_threads=threads), downscale=downscale)
    err = _centre_error(rec, {f"{i:03d}.png": c for i, c in enumerate(room.cameras)})
    row = _sfm_row("synthetic", rec, err, room.cameras[0].K[0, 0], "units")
    al = err["alignment"]
    true_cams = [room.cameras[int(c.name[:3])].scaled(1 / downscale) for c in rec.cameras]
    moved = [al.apply_to_camera(c) for c in rec.cameras]
    kept = dict(images=rec.images[::2], masks=rec.masks[::2], points=al.apply(rec.points),
                point_colors=rec.point_colors)
    # controlled: the recovered cameras moved into the true frame (same normalisation, same random
    # draws; only the cameras differ); recovered_true_intrinsics: their poses with the true K and no
    # distortion (which part of the gap the intrinsics make); sfm_frame: the fit as a user runs it,
    # in the model's frame, its mesh mapped into the true frame by the centres' similarity afterwards
    scenes_by_label = {
        "true": (Scene(true_cams[::2], **kept), None),
        "recovered": (Scene(moved[::2], **kept), None),
        "recovered_true_intrinsics": (Scene([_camera(t, t.K, m.world_to_camera, None)
                                             for t, m in zip(true_cams, moved)][::2], **kept), None),
        "recovered_sfm_frame": (Scene(rec.cameras[::2], rec.images[::2], masks=rec.masks[::2], points=rec.points,
                                      point_colors=rec.point_colors), al.apply)}
    for label in variants:
        s, to_true = scenes_by_label[label]
        for seed in seeds:
            cfg = small_fit_config(warmup, coevolution, points=600, grids=(48, 64, 32), max_faces=1500,
                                   density_every=10, eval_every=0)
            cfg.runtime.seed = seed
            t = time.perf_counter()
            mesh = fit(s, cfg, progress=False).mesh
            secs = round(time.perf_counter() - t, 1)
            if to_true is not None:
                mesh = trimesh.Trimesh(to_true(mesh.vertices), mesh.faces, process=False)
            g = geometry_metrics(mesh, gt)
            # Tanks and Temples: the camera alignment refined by ICP against the truth
            ref = refine_alignment(mesh, gt)
            gr = geometry_metrics(ref.apply_to_mesh(mesh), gt)
            row[f"fit_{label}_seed{seed}"] = r = {
                "s": secs, "chamfer_pct": round(100 * g["chamfer_rel"], 4), "f_score": round(g["f_score"], 3),
                "refined_chamfer_pct": round(100 * gr["chamfer_rel"], 4), "refined_f_score": round(gr["f_score"], 3),
                "refinement_scale": round(ref.scale, 5)}
            print(label, seed, json.dumps(r), flush=True)
    for key in ("chamfer_pct", "refined_chamfer_pct"):
        mean = {label: float(np.mean([row[f"fit_{label}_seed{k}"][key] for k in seeds])) for label in variants}
        if "true" in mean:
            row[f"ratio_to_true_{key}"] = {label: round(m / mean["true"], 3) for label, m in mean.items()}
    print(json.dumps({k: v for k, v in row.items() if k.startswith("ratio")}, indent=1), flush=True)
    return row


def dtu(threads: int, work: str, do_fit: bool, sets: list[str], variants: list[str]) -> dict:
    from wtopo.cli import _apply_set

    given = load_scene(DTU)  # DTU world, millimetres
    # undistort=False: the "recovered" fit takes DTU's photos as they are with the recovered cameras,
    # lens (SIMPLE_RADIAL k) included
    rec = load_photos(os.path.join(DTU, "image"), out_dir=os.path.join(work, "dtu"),
                      options=SfMOptions(num_threads=threads), undistort=False)
    err = _centre_error(rec, {c.name: c for c in given.cameras})
    row = _sfm_row("dtu_scan24", rec, err, given.cameras[0].K[0, 0], "mm")
    if not do_fit:
        return row
    al = err["alignment"]
    # controlled, as on the synthetic capture: the recovered cameras (intrinsics, distortion, poses)
    # moved into DTU's frame by the centres' similarity; held-out split and region of interest
    # (scale_mat) are the given scene's, so only the cameras differ ("recovered"), or the cameras and
    # the photos undistorted to them ("recovered_undistorted", what load_photos gives by default)
    by_name = {c.name: c for c in rec.cameras}
    order = [c.name for c in given.cameras]
    scenes_by_label = {"given": lambda: given,
                       "recovered": lambda: dataclasses.replace(
                           given, cameras=[al.apply_to_camera(by_name[n]) for n in order])}

    def undistorted():
        u = load_photos(os.path.join(DTU, "image"), out_dir=os.path.join(work, "dtu"), progress=False)
        idx = {c.name: i for i, c in enumerate(u.cameras)}
        images = np.asarray(u.images)[[idx[n] for n in order]]
        return dataclasses.replace(given, cameras=[al.apply_to_camera(u.cameras[idx[n]]) for n in order],
                                   images=images)

    scenes_by_label["recovered_undistorted"] = undistorted
    meshes = {}
    for label in DTU_VARIANTS:
        path = os.path.join(work, "dtu", f"fit_{label}.ply")
        if label in variants:
            cfg = FitConfig()
            for item in sets:
                _apply_set(cfg, item)
            cfg.runtime.progress = False
            t = time.perf_counter()
            res = fit(scenes_by_label[label](), cfg, progress=False)
            res.mesh.export(path)
            row[f"fit_{label}"] = {"s": round(time.perf_counter() - t, 1), "psnr": round(res.report.get("psnr", 0), 2),
                                   "ssim": round(res.report.get("ssim", 0), 3), "faces": len(res.mesh.faces)}
            print(label, json.dumps(row[f"fit_{label}"]), flush=True)
        if os.path.isfile(path):  # an earlier run's mesh (--work) takes part in the comparison
            meshes[label] = trimesh.load(path, process=False)
    for label in ("recovered", "recovered_undistorted"):
        if label not in meshes or "given" not in meshes:
            continue
        c = chamfer(meshes[label], meshes["given"])
        ref = refine_alignment(meshes[label], meshes["given"])
        c_ref = chamfer(ref.apply_to_mesh(meshes[label]), meshes["given"])
        row[f"mesh_to_mesh_{label}"] = {
            "chamfer_mm": round(c.chamfer, 3), "chamfer_pct_diag": round(100 * c.chamfer_rel, 4),
            "refined_chamfer_mm": round(c_ref.chamfer, 3),
            "refined_chamfer_pct_diag": round(100 * c_ref.chamfer_rel, 4),
            "refinement": {"scale": round(ref.scale, 5), "moved_mm": round(_motion(ref, meshes["given"]), 3)}}
    print(json.dumps({k: v for k, v in row.items() if k.startswith(("fit_", "mesh_"))}, indent=1), flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--threads", type=int, default=2, help="CPU threads for pycolmap")
    p.add_argument("--skip-synthetic", action="store_true")
    p.add_argument("--skip-dtu", action="store_true")
    p.add_argument("--dtu-fit", action="store_true", help="also fit DTU from both camera sets")
    p.add_argument("--dtu-set", action="append", default=[], metavar="PATH=VALUE",
                   help="FitConfig override of the DTU fits, as wtopo fit --set (e.g. warmup.iterations=150)")
    p.add_argument("--dtu-variants", nargs="+", default=list(DTU_VARIANTS), choices=DTU_VARIANTS,
                   help="camera sets of the DTU fits (with --work, earlier fits' meshes join the comparison)")
    p.add_argument("--work", help="keep the photos and models here (a rerun reuses them) instead of a temporary folder")
    p.add_argument("--fit-iterations", type=int, nargs=2, default=(150, 50), metavar=("WARMUP", "COEVOLUTION"),
                   help="iterations of the synthetic fits (default: the test's)")
    p.add_argument("--fit-seeds", type=int, nargs="+", default=[0, 1], help="seeds of each synthetic fit")
    p.add_argument("--fit-variants", nargs="+", default=list(SYNTHETIC_VARIANTS), choices=SYNTHETIC_VARIANTS,
                   help="camera sets of the synthetic fits")
    p.add_argument("--fit-downscale", type=int, default=4, help="synthetic fits on 256 / F px images (the test: 8)")
    p.add_argument("--json", help="write the rows here")
    a = p.parse_args()
    print(f"load average at start: {os.getloadavg()}", flush=True)
    rows = []
    with contextlib.ExitStack() as stack:
        work = a.work or stack.enter_context(tempfile.TemporaryDirectory(prefix="wtopo_sfm_bench_"))
        if not a.skip_synthetic:
            rows.append(synthetic(a.threads, work, *a.fit_iterations, a.fit_downscale, a.fit_seeds,
                                   a.fit_variants))
        if not a.skip_dtu:
            rows.append(dtu(a.threads, work, a.dtu_fit, a.dtu_set, a.dtu_variants))
    print(f"load average at end: {os.getloadavg()}", flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
