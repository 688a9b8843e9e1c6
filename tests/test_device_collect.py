# SPDX-License-Identifier: Apache-2.0
"""benchmarks/device/collect.py: the loop against no loop from a device batch's rows and reports."""

import importlib.util
import json
import pathlib

import numpy as np
import pytest

_PATH = pathlib.Path(__file__).parents[1] / "benchmarks" / "device" / "collect.py"


@pytest.fixture(scope="module")
def collect():
    spec = importlib.util.spec_from_file_location("device_collect", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _batch(root: pathlib.Path, fits) -> None:
    """hard.py's layout: <label>/rows.json and <label>/seed<S>/<scene>_<variant>/report.json per fit."""
    for i, (variant, seed, faces, chamfer) in enumerate(fits):
        label = root / f"b{i}"
        fit = label / f"seed{seed}" / f"cup_{variant}"
        fit.mkdir(parents=True)
        events = [{"event": "densify"}] if faces is None else [{"event": "tsdf_reinit", "reinit_faces": faces}]
        (fit / "report.json").write_text(json.dumps({"events": events}))
        row = {"scene": "cup", "variant": variant, "seed": seed, "chamfer": chamfer, "obs_chamfer": chamfer / 2}
        (label / "rows.json").write_text(json.dumps([row]))


def test_the_effect_at_equal_reinitialisation_is_recovered(collect, tmp_path):
    """Chamfer = 0.2 + 0.01 per 1,000 re-initialisation faces + 0.05 with the loop: the raw change mixes
    in the re-initialisations' spread, the adjusted one is the loop's 0.05 exactly, in % of no loop's mean."""
    rng = np.random.default_rng(0)
    fits = []
    for seed in range(6):
        for variant in ("default", "no_loop"):
            faces = int(rng.integers(150_000, 200_000))
            fits.append((variant, seed, faces, 0.2 + 0.01 * faces / 1e3 + (0.05 if variant == "default" else 0.0)))
    fits.append(("no_loop", 9, None, 5.0))  # no re-initialisation event: left out of the adjustment only
    _batch(tmp_path, fits)
    rows = collect.load_rows([str(tmp_path)])
    assert len(rows) == 13 and sum(r["reinit_faces"] is None for r in rows) == 1
    eff, se, n, corr = collect.adjusted(rows)["cup"]
    base = np.mean([f[3] for f in fits[:-1] if f[0] == "no_loop"])
    assert n == 12 and se < 1e-6 and corr > 0.9
    assert eff == pytest.approx(100 * 0.05 / base, rel=1e-9)
    assert collect.adjusted(rows, key="obs_chamfer")["cup"][0] == pytest.approx(100 * 0.025 / (base / 2), rel=1e-9)
    text = collect.adjusted_table(rows)
    assert "| cup | 12 |" in text and f"{eff:+.1f} +- 0.0 %" in text


def test_too_few_fits_are_not_adjusted(collect, tmp_path):
    """Three fits, or one variant only, give no adjusted row rather than a fit of noise."""
    _batch(tmp_path, [("default", 0, 160_000, 1.0), ("no_loop", 0, 170_000, 1.1), ("default", 1, 180_000, 1.2)])
    assert collect.adjusted(collect.load_rows([str(tmp_path)])) == {}
