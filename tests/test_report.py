# SPDX-License-Identifier: Apache-2.0
"""Tests for wtopo.report: contact sheet of the timeline (mesh ray caster), error plot, report(run_dir)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from wtopo.report import contact_sheet, error_plot, report

pytest.importorskip("pxr")
from test_io import ITERATIONS, write_timeline  # noqa: E402  (the timeline every io test reads)

TILE = 64  # tile size in pixels: small keeps the CPU ray casting fast, large enough to hit every mesh


def _history(n=60):
    return [{"iteration": i, "stage": "warmup" if i < 20 else "coevolve", "elapsed": 0.05 * i,
             "losses": {"rgb": 1.0 / (i + 1), "normal": 0.3 / (i + 2)},
             **({"chamfer": 0.1 / (i + 1), "f_score": i / 60, "psnr": 20 + i / 6} if i % 10 == 0 else {})}
            for i in range(n)]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    write_timeline(str(d / "timeline.usdc"), n_surfels=(5,) * len(ITERATIONS), splats=False)
    (d / "history.json").write_text(json.dumps(_history()))
    return d


def _tile(img: np.ndarray, k: int, cols: int) -> np.ndarray:
    h = TILE + 16  # tile plus caption strip (report._LABEL_HEIGHT)
    return img[(k // cols) * h:(k // cols) * h + TILE, (k % cols) * TILE:(k % cols + 1) * TILE]


def test_contact_sheet_is_not_blank(run_dir, tmp_path):
    """Render every requested iteration and the static meshes into non-blank, distinct tiles."""
    out = contact_sheet(run_dir, tmp_path / "sheet.png", iterations=[0, 25, 50], size=TILE)
    img = np.asarray(Image.open(out).convert("RGB")).astype(np.float64)
    # 3 iterations + ground_truth + final = 5 tiles on a 3 x 2 grid
    assert img.shape == (2 * (TILE + 16), 3 * TILE, 3)
    assert img.std() > 0
    tiles = [_tile(img, k, 3) for k in range(5)]
    for t in tiles:
        assert (t < 250).any(axis=2).mean() > 0.05, "each tile must show its mesh"
    assert np.abs(tiles[0] - tiles[2]).max() > 0, "icosphere levels 1 and 2 must render differently"


def test_contact_sheet_picks_iterations(run_dir, tmp_path):
    """Pick the mesh samples by default and reject an iteration before the first sample."""
    img = np.asarray(Image.open(contact_sheet(run_dir / "timeline.usdc", tmp_path / "a.png", size=TILE)))
    assert img.shape[:2] == (3 * (TILE + 16), 3 * TILE)  # 6 samples + 2 static meshes = 8 tiles, 3 x 3
    with pytest.raises(ValueError, match="precedes"):
        contact_sheet(run_dir, tmp_path / "b.png", iterations=[-5], size=TILE)


@pytest.mark.parametrize("kind", ["json", "csv", "records"])
def test_error_plot(tmp_path, kind):
    """Plot losses and metrics from history.json, a CSV file or records."""
    hist = _history()
    if kind == "json":
        src = tmp_path / "history.json"
        src.write_text(json.dumps(hist))
    elif kind == "csv":
        src = tmp_path / "history.csv"
        cols = ["iteration", "stage", "elapsed", "loss_rgb", "loss_normal", "chamfer", "f_score", "psnr"]
        rows = [",".join(cols)] + [",".join(str(r.get(c, r["losses"].get(c[5:], ""))) for c in cols) for r in hist]
        src.write_text("\n".join(rows))
    else:
        src = hist
    img = np.asarray(Image.open(error_plot(src, tmp_path / "err.png")).convert("L"), dtype=np.float64)
    assert img.shape[1] > img.shape[0] and img.std() > 0  # four panels side by side


def test_error_plot_needs_data(tmp_path):
    """Reject a history without losses or metrics."""
    with pytest.raises(ValueError, match="no losses"):
        error_plot([{"iteration": 0, "elapsed": 0.0}], tmp_path / "e.png")


def test_report_writes_both(run_dir):
    """Write contact_sheet.png and error.png into the run directory."""
    out = report(run_dir, size=TILE)
    assert set(out) == {"contact_sheet", "error_plot"}
    for p in out.values():
        assert np.asarray(Image.open(p)).std() > 0
