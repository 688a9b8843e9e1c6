# SPDX-License-Identifier: Apache-2.0
"""One scorer for every system of the peers benchmark.

For each result folder (``mesh.ply``, ``renders.npz``, ``run.json``) of one exchange folder:

* against the ground-truth mesh (when the scene has one): Chamfer, accuracy, completeness (each as
  a percentage of the ground truth's bounding-box diagonal) and F-score at 0.5 % of it; for a scene
  with a region of interest (the unbounded scenes, whose truth runs to the horizon) the ROI precision,
  recall and F-score instead (Tanks-and-Temples, :func:`wtopo.metrics.roi_f_score`, at 0.5 % of the
  box's diagonal, against all the truth's geometry);
* held-out PSNR and SSIM: inside the masks for masked captures (the IDR / NeuS convention; SSIM of
  both images composited on black), the whole image otherwise;
* the mesh's silhouette IoU against the held-out masks (masked captures);
* wall time from images to mesh, peak GPU memory, face count and whether the mesh is watertight.

    python benchmarks/peers/score.py EXCH RESULT [RESULT ...] --out rows.json [--pictures DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _result import read_json  # noqa: E402
from exchange import load  # noqa: E402

F_TAU = 0.005  # F-score threshold, fraction of the ground truth's diagonal


def image_scores(renders: np.ndarray, ex) -> dict:
    """Mean held-out PSNR [dB] and SSIM of ``renders`` [T, H, W, 3] against the exchange folder's test views, and
    each view's PSNR (``psnr_views``, in the order of ``ex.test``: a mean can hide one extrapolated view)."""
    from wtopo import metrics

    p, s = [], []
    for r, i in zip(renders, ex.test):
        pred = torch.from_numpy(np.asarray(r, dtype=np.float32))
        gt = torch.from_numpy(ex.image(i))
        m = ex.mask(i)
        if m is not None:
            mt = torch.from_numpy(m)
            p.append(float(metrics.psnr(pred, gt, mask=mt)))
            s.append(float(metrics.ssim(pred * mt[..., None], gt * mt[..., None])))
        else:
            p.append(float(metrics.psnr(pred, gt)))
            s.append(float(metrics.ssim(pred, gt)))
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s)), "psnr_on": "masks" if ex.masked else "image",
            "psnr_views": [round(x, 2) for x in p]}


def silhouette_iou(mesh, ex) -> float | None:
    """Mean IoU of the mesh's ray-cast silhouette and the held-out masks (``None`` without masks)."""
    if not ex.masked or len(mesh.faces) == 0:
        return None
    from wtopo import ops

    v = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    f = torch.tensor(np.asarray(mesh.faces), dtype=torch.int32)
    hits = ops.raycast_mesh(v, f, [ex.camera(i) for i in ex.test]).mask.cpu().numpy().astype(bool)  # one BVH
    ious = [float((hit & m).sum() / max((hit | m).sum(), 1)) for hit, m in zip(hits, (ex.mask(i) for i in ex.test))]
    return float(np.mean(ious))


def geometry_scores(mesh, gt) -> dict:
    from wtopo import metrics

    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    ch = metrics.chamfer(mesh, gt, n_samples=200_000, seed=0)
    fs = metrics.f_score(mesh, gt, F_TAU * diag, n_samples=200_000, seed=0)
    return {"chamfer_pct": 100 * ch.chamfer_rel, "accuracy_pct": 100 * ch.accuracy_rel,
            "completeness_pct": 100 * ch.completeness_rel, "f_score": fs.f_score}


def roi_scores(mesh, gt, lower, upper) -> dict:
    """ROI precision, recall and F-score of ``mesh`` at 0.5 % of the box's diagonal (``wtopo.metrics.roi_f_score``)."""
    from wtopo import metrics

    tau = F_TAU * float(np.linalg.norm(upper - lower))
    f = metrics.roi_f_score(mesh, gt, lower, upper, tau, n_samples=200_000, seed=0)
    return {"roi_precision": f.precision, "roi_recall": f.recall, "roi_f1": f.f_score}


def score(exchange: str, result: str) -> dict:
    import trimesh

    ex = load(exchange)
    run = read_json(os.path.join(result, "run.json"))
    mesh = trimesh.load(os.path.join(result, "mesh.ply"), process=False)
    row = {"scene": ex.meta["name"], "system": run["system"], "wall_s": run.get("wall_s"),
           "peak_gpu_gib": run["peak_gpu_bytes"] / 2 ** 30 if run.get("peak_gpu_bytes") else None,
           "iterations": run.get("iterations"), "faces": int(len(mesh.faces)),
           "watertight": bool(mesh.is_watertight) if len(mesh.faces) else False}
    row.update(image_scores(np.load(os.path.join(result, "renders.npz"))["rgb"], ex))
    row["silhouette_iou"] = silhouette_iou(mesh, ex)
    gt, roi = ex.gt(), ex.roi()
    if gt is not None and roi is not None:
        row.update(roi_scores(mesh, gt, *roi))  # an empty mesh scores 0
    elif gt is not None and len(mesh.faces):
        row.update(geometry_scores(mesh, gt))
    return row


def _tile(img: np.ndarray, label: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    im = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
    ImageDraw.Draw(im).text((4, 4), label, fill=(255, 0, 0))
    return np.asarray(im)


def pictures(exchange: str, results: list[str], out: str, views: int = 2) -> str:
    """Every system's mesh, normal-shaded, from the first ``views`` held-out views, beside the photo."""
    import trimesh
    from PIL import Image

    from wtopo import ops

    ex = load(exchange)
    shown = ex.test[:views]
    columns = [[(ex.image(i), "photo") for i in shown]]  # per system, one tile per view
    for r in results:
        mesh = trimesh.load(os.path.join(r, "mesh.ply"), process=False)
        name = read_json(os.path.join(r, "run.json"))["system"]
        blank = np.ones((ex.height, ex.width, 3), np.float32)
        if not len(mesh.faces):
            columns.append([(blank, name) for _ in shown])
            continue
        v = torch.tensor(np.asarray(mesh.vertices), dtype=torch.float32)
        f = torch.tensor(np.asarray(mesh.faces), dtype=torch.int32)
        rr = ops.raycast_mesh(v, f, [ex.camera(i) for i in shown])  # one BVH for every view
        normals, masks = rr.normal.cpu().numpy(), rr.mask.cpu().numpy()
        tiles = []
        for k, i in enumerate(shown):
            n = normals[k] @ ex.w2c[i][:3, :3].T  # camera frame
            shade = np.clip(-n[..., 2:3], 0, 1) * 0.8 + 0.2
            tiles.append((np.where(masks[k][..., None], shade * np.array([0.9, 0.85, 0.75]), blank), name))
        columns.append(tiles)
    cols = [np.concatenate([_tile(t, label) for t, label in (c[k] for c in columns)], axis=1)
            for k in range(len(shown))]
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{ex.meta['name']}.png")
    Image.fromarray(np.concatenate(cols, axis=0)).save(path)
    return path


def render_pictures(exchange: str, results: list[str], out: str, gain: float = 4.0) -> str:
    """Every held-out view as rows of tiles: the photo, each system's render, then each system's absolute error
    times ``gain`` (inside the mask for a masked capture, as the PSNR is taken), each labelled with its system and
    that view's PSNR [dB]. Where one system's renders lose to another's (#59) the error tiles show what: blur,
    colour, a missing part or a view-dependent halo. Returns the PNG's path (``out/<scene>_renders.png``)."""
    from PIL import Image

    from wtopo import metrics

    ex = load(exchange)
    rows = []
    systems = [(read_json(os.path.join(r, "run.json"))["system"], np.load(os.path.join(r, "renders.npz"))["rgb"])
               for r in results]
    for k, i in enumerate(ex.test):
        gt = ex.image(i).astype(np.float32)
        m = ex.mask(i)
        keep = np.ones(gt.shape[:2], bool) if m is None else m.astype(bool)
        renders, errors = [], []
        for name, rgb in systems:
            pred = rgb[k].astype(np.float32)
            err = np.where(keep[..., None], np.abs(pred - gt), 0.0)
            db = float(metrics.psnr(torch.from_numpy(pred), torch.from_numpy(gt),
                                    mask=None if m is None else torch.from_numpy(m)))  # as image_scores takes it
            renders.append(_tile(pred, f"{name} {db:.2f} dB"))
            errors.append(_tile(err * gain, f"{name} |error| x{gain:g}"))
        rows.append(np.concatenate([_tile(gt, f"photo, view {i}"), *renders, *errors], axis=1))
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{ex.meta['name']}_renders.png")
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)
    return path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exchange")
    ap.add_argument("results", nargs="+")
    ap.add_argument("--out", required=True, help="rows are appended to this JSON list")
    ap.add_argument("--pictures", default=None, help="folder for every system's mesh beside the photos")
    ap.add_argument("--render-pictures", default=None,
                    help="folder for every held-out view's photo, each system's render and its error")
    a = ap.parse_args(argv)
    rows = read_json(a.out) if os.path.exists(a.out) else []
    for r in a.results:
        if not os.path.exists(os.path.join(r, "run.json")):
            print(f"skip {r}: no run.json", file=sys.stderr)
            continue
        row = score(a.exchange, r)
        print(json.dumps(row))
        rows.append(row)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(rows, f, indent=1)
    if a.pictures:
        ok = [r for r in a.results if os.path.exists(os.path.join(r, "run.json"))]
        print(pictures(a.exchange, ok, a.pictures))
    if a.render_pictures:
        ok = [r for r in a.results if os.path.exists(os.path.join(r, "renders.npz"))]
        print(render_pictures(a.exchange, ok, a.render_pictures))


if __name__ == "__main__":
    main()
