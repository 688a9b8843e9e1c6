# SPDX-License-Identifier: Apache-2.0
"""Look at a run without usdview: a PNG contact sheet of the proxy mesh over the timeline and an
error-against-time plot.

A run directory holds ``timeline.usdc`` (written by :class:`wtopo.io.TimelineWriter`) and
``history.json``: a list of records ``{"iteration": int, "stage": str, "elapsed": seconds,
"losses": {name: float}, "chamfer"?: float, "f_score"?: float, "psnr"?: float, "ssim"?: float}``.
``wtopo report RUN_DIR`` calls :func:`report`; ``wtopo export`` calls :func:`wtopo.io.export`.
"""

from __future__ import annotations

import csv
import json
import math
import os

import numpy as np

from .io._common import atomic_write
from .io.usd import Timeline, mesh_at, read_timeline

__all__ = ["contact_sheet", "error_plot", "report", "load_history", "TIMELINE_NAME", "HISTORY_NAME"]

TIMELINE_NAME = "timeline.usdc"
"""File name of the USD timeline inside a run directory."""

HISTORY_NAME = "history.json"
"""File name of the per-iteration history inside a run directory."""

METRICS = ("chamfer", "f_score", "psnr", "ssim")
"""Optional evaluation entries of a history record, each plotted in its own panel."""

_LABEL_HEIGHT = 16  # pixels of the caption strip under each tile (the default PIL font is 11 px high)
_BACKGROUND = 255  # white tiles behind the mesh
_MAX_AUTO_TILES = 8  # iterations picked when none are requested


def _timeline_path(run_dir_or_usd: str | os.PathLike) -> str:
    p = os.fspath(run_dir_or_usd)
    if os.path.isdir(p):
        p = os.path.join(p, TIMELINE_NAME)
    if not os.path.exists(p):
        raise FileNotFoundError(f"no USD timeline at {p}")
    return p


def _view_camera(boxes: list[np.ndarray], up_axis: str, size: int):
    """A camera seeing every box ([2, 3] min/max) from the front-right-above, square image of ``size``."""
    from .camera import Camera

    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    up = np.array([0.0, 1.0, 0.0]) if up_axis == "Y" else np.array([0.0, 0.0, 1.0])
    side = np.array([1.0, 0.0, 0.0])
    front = np.cross(side, up)  # +z for Y-up, -y for Z-up
    direction = 0.8 * front + 0.6 * side + 0.5 * up
    direction /= np.linalg.norm(direction)
    fov = math.radians(40.0)
    eye = centre + direction * radius / math.sin(0.5 * fov) * 1.05  # whole bounding sphere in view
    return Camera.look_at(eye, centre, up, fov_x=fov, width=size, height=size)


def _render_tile(verts: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """Normal-shaded render [H, W, 3] uint8: camera-space normals as an OpenGL-style normal map."""
    import torch

    from .ops import raycast_mesh

    h, w = camera.height, camera.width
    img = np.full((h, w, 3), _BACKGROUND, np.uint8)
    if len(faces) == 0:
        return img
    with torch.no_grad():
        r = raycast_mesh(torch.tensor(verts, dtype=torch.float32), torch.tensor(faces, dtype=torch.int32),
                         camera)
    mask = r.mask.cpu().numpy()
    n_cam = r.normal.cpu().numpy().astype(np.float64) @ camera.R.T  # world -> OpenCV camera axes
    n_cam *= np.where((n_cam[..., 2:] > 0), -1.0, 1.0)  # face the viewer: back faces shaded as front
    rgb = 0.5 + 0.5 * n_cam * np.array([1.0, -1.0, -1.0])  # to OpenGL axes: facing the camera = blue
    img[mask] = np.clip(rgb[mask] * 255 + 0.5, 0, 255).astype(np.uint8)
    return img


def _pick_iterations(timeline: Timeline, iterations) -> list[int]:
    with_mesh = [s.iteration for s in timeline.samples if len(s.faces)]
    if iterations is not None:
        return [int(i) for i in iterations]
    if len(with_mesh) <= _MAX_AUTO_TILES:
        return with_mesh
    idx = np.linspace(0, len(with_mesh) - 1, _MAX_AUTO_TILES).round().astype(int)
    return [with_mesh[i] for i in idx]


def contact_sheet(run_dir_or_usd: str | os.PathLike, out_png: str | os.PathLike, *, iterations=None,
                  size: int = 256, camera=None) -> str:
    """Render the proxy mesh at chosen iterations (plus the static meshes) into one labelled PNG.

    Each tile is the mesh ray cast with :func:`wtopo.ops.raycast_mesh` and shaded by its normal
    in camera axes (normal-map colours); every tile uses the same camera, so tiles compare.

    Args:
        run_dir_or_usd: a run directory (holding ``timeline.usdc``) or a USD timeline file.
        out_png: output PNG path.
        iterations: iterations to show (each tile holds the latest mesh sample at or before it);
            ``None`` picks up to 8 evenly spread samples, first and last included.
        size: tile width and height in pixels.
        camera: a :class:`wtopo.Camera` to render from (its size replaces ``size``); ``None``
            frames every shown mesh from above-front-right, honouring the stage up axis.

    Returns:
        ``out_png`` as a string.

    Raises:
        FileNotFoundError: no timeline.
        ValueError: ``size`` < 16, a requested iteration before the first mesh sample, nothing to show.
    """
    from PIL import Image, ImageDraw, ImageFont

    if isinstance(size, bool) or int(size) != size or size < 16:
        raise ValueError(f"size must be an integer >= 16, got {size!r}")
    tl = read_timeline(_timeline_path(run_dir_or_usd))
    tiles = []
    for it in _pick_iterations(tl, iterations):
        v, f = mesh_at(tl, it)
        tiles.append((f"iter {it}  V {len(v)}  F {len(f)}", v, f))
    for name, (v, f) in tl.meshes.items():
        tiles.append((f"{name}  V {len(v)}  F {len(f)}", v, f))
    if not tiles:
        raise ValueError(f"{run_dir_or_usd}: the timeline holds no mesh to show")
    if camera is None:
        boxes = [np.stack([v.min(0), v.max(0)]) for _, v, f in tiles if len(f)]
        camera = _view_camera(boxes or [np.array([[-1.0] * 3, [1.0] * 3])], tl.up_axis, int(size))
    w, h = camera.width, camera.height
    cols = math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / cols)
    sheet = Image.new("RGB", (cols * w, rows * (h + _LABEL_HEIGHT)), (_BACKGROUND,) * 3)
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    for k, (label, v, f) in enumerate(tiles):
        x, y = (k % cols) * w, (k // cols) * (h + _LABEL_HEIGHT)
        sheet.paste(Image.fromarray(_render_tile(v, f, camera)), (x, y))
        draw.text((x + 3, y + h + 2), label, fill=(0, 0, 0), font=font)
    out_png = os.fspath(out_png)
    atomic_write(out_png, lambda tmp: sheet.save(tmp, format="PNG"), suffix=".png")
    return out_png


def load_history(history) -> list[dict]:
    """History records from a ``history.json`` list, a CSV file, or a list of dicts.

    CSV columns: ``iteration``, ``stage``, ``elapsed``, the metrics, and one ``loss_<name>``
    (or ``losses.<name>``) column per loss; empty cells are missing values.
    """
    if isinstance(history, (list, tuple)):
        return [dict(r) for r in history]
    path = os.fspath(history)
    if os.path.isdir(path):
        path = os.path.join(path, HISTORY_NAME)
    if path.lower().endswith(".csv"):
        records = []
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                rec, losses = {}, {}
                for k, v in row.items():
                    if v in (None, ""):
                        continue
                    if k.startswith(("loss_", "losses.")):
                        losses[k.split("_", 1)[1] if k.startswith("loss_") else k.split(".", 1)[1]] = float(v)
                    else:
                        try:
                            rec[k] = float(v)
                        except ValueError:  # stage names and other text columns
                            rec[k] = v
                rec["losses"] = losses
                records.append(rec)
        return records
    with open(path) as f:
        data = json.load(f)
    if not isinstance(data, list):
        raise ValueError(f"{path} must hold a JSON list of records, got {type(data).__name__}")
    return data


def _series(records: list[dict], x_key: str, get) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = [], []
    for r in records:
        y = get(r)
        if y is not None and x_key in r and math.isfinite(float(y)):
            xs.append(float(r[x_key]))
            ys.append(float(y))
    return np.asarray(xs), np.asarray(ys)


def error_plot(history_csv_or_json, out_png: str | os.PathLike) -> str:
    """Plot losses and evaluation metrics against elapsed time (matplotlib, no pyplot state).

    One panel for the losses (log scale when all positive), one per metric present
    (:data:`METRICS`); dashed vertical lines mark stage changes.  Records without ``elapsed``
    are plotted against ``iteration`` instead.

    Args:
        history_csv_or_json: ``history.json`` / ``.csv`` path, a run directory, or a list of records.
        out_png: output PNG path.

    Returns:
        ``out_png`` as a string.

    Raises:
        ValueError: no record holds a loss or a metric.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    records = load_history(history_csv_or_json)
    x_key = "elapsed" if records and all("elapsed" in r for r in records) else "iteration"
    loss_names = sorted({k for r in records for k in (r.get("losses") or {})})
    metrics = [m for m in METRICS if any(r.get(m) is not None for r in records)]
    if not loss_names and not metrics:
        raise ValueError("history holds no losses and no metrics to plot")
    panels = (["losses"] if loss_names else []) + metrics
    fig = Figure(figsize=(5.0 * len(panels), 3.6), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    changes = [(float(b[x_key]), b.get("stage", "")) for a, b in zip(records, records[1:])
               if a.get("stage") != b.get("stage") and x_key in b]
    for ax, panel in zip(axes, panels):
        if panel == "losses":
            positive = True
            for name in loss_names:
                x, y = _series(records, x_key, lambda r, n=name: (r.get("losses") or {}).get(n))
                ax.plot(x, y, label=name, linewidth=1.2)
                positive &= bool(len(y) == 0 or y.min() > 0)
            if positive:
                ax.set_yscale("log")
            ax.legend(fontsize=7)
            ax.set_title("losses")
        else:
            x, y = _series(records, x_key, lambda r, m=panel: r.get(m))
            ax.plot(x, y, marker="o", markersize=3, linewidth=1.2)
            ax.set_title(panel)
        for xc, stage in changes:
            ax.axvline(xc, color="0.5", linestyle="--", linewidth=0.8)
            ax.annotate(stage, (xc, 1.0), xycoords=("data", "axes fraction"), fontsize=7, rotation=90,
                        va="top", ha="right", color="0.4")
        ax.set_xlabel("elapsed [s]" if x_key == "elapsed" else "iteration")
        ax.grid(True, alpha=0.3)
    out_png = os.fspath(out_png)
    atomic_write(out_png, lambda tmp: fig.savefig(tmp, format="png"), suffix=".png")
    return out_png


def report(run_dir: str | os.PathLike, *, iterations=None, size: int = 256) -> dict[str, str]:
    """Write ``contact_sheet.png`` and (when ``history.json`` exists) ``error.png`` into ``run_dir``.

    Returns:
        ``{"contact_sheet": path, "error_plot": path}`` for the files written.

    Raises:
        FileNotFoundError: ``run_dir`` holds neither a timeline nor a history.
    """
    run_dir = os.fspath(run_dir)
    out = {}
    if os.path.exists(os.path.join(run_dir, TIMELINE_NAME)):
        out["contact_sheet"] = contact_sheet(run_dir, os.path.join(run_dir, "contact_sheet.png"),
                                             iterations=iterations, size=size)
    if os.path.exists(os.path.join(run_dir, HISTORY_NAME)):
        out["error_plot"] = error_plot(os.path.join(run_dir, HISTORY_NAME), os.path.join(run_dir, "error.png"))
    if not out:
        raise FileNotFoundError(f"{run_dir} holds neither {TIMELINE_NAME} nor {HISTORY_NAME}")
    return out
