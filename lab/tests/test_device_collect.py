# SPDX-License-Identifier: Apache-2.0
"""lab/device/collect.py: the loop against no loop from a device batch's rows and reports."""

import importlib.util
import json
import os
import pathlib
import subprocess

import numpy as np
import pytest

_PATH = pathlib.Path(__file__).parents[2] / "lab" / "device" / "collect.py"


@pytest.fixture(scope="module")
def collect():
    spec = importlib.util.spec_from_file_location("device_collect", _PATH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _batch(root: pathlib.Path, fits, starts=None, extra=None) -> None:
    """hard.py's layout: <label>/rows.json and <label>/seed<S>/<scene>_<variant>/report.json per fit;
    ``starts[i]``: the warm-up fit i branched from (its report's ``started_from`` event), ``extra[i]``: more
    measures of its row."""
    for i, (variant, seed, faces, chamfer) in enumerate(fits):
        label = root / f"b{i}"
        fit = label / f"seed{seed}" / f"cup_{variant}"
        fit.mkdir(parents=True)
        events = [{"event": "densify"}] if faces is None else [{"event": "tsdf_reinit", "reinit_faces": faces}]
        if starts is not None and starts[i] is not None:
            events.insert(0, {"event": "started_from", "from": starts[i]})
        (fit / "report.json").write_text(json.dumps({"events": events}))
        row = {"scene": "cup", "variant": variant, "seed": seed, "chamfer": chamfer, "obs_chamfer": chamfer / 2,
               **(extra[i] if extra else {})}
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


def test_pairs_compare_only_fits_from_one_warm_up(collect, tmp_path):
    """Each warm-up's loop fit is 10 % above its no-loop fit on the Chamfer and 20 % below on the floaters,
    whatever the warm-up's own level: the pairs read exactly that, with no spread. A fit from a warm-up with no
    partner (w3), and one that started from none, pair with nothing."""
    fits, starts, extra = [], [], []
    for w, level in (("w0", 1.0), ("w1", 1.4), ("w2", 0.7)):
        for variant, f in (("default", 1.1), ("no_loop", 1.0)):
            fits.append((variant, int(w[1]), 100_000, level * f))
            starts.append(f"/stage/{w}/ckpt.pt")
            extra.append({"floater_frac": 30.0 * (0.8 if variant == "default" else 1.0)})
    fits += [("default", 3, 100_000, 9.0), ("no_loop", 4, 100_000, 0.1)]
    starts += ["/stage/w3/ckpt.pt", None]
    extra += [{}, {}]
    _batch(tmp_path, fits, starts, extra)
    rows = collect.load_rows([str(tmp_path)])
    res = collect.paired(rows)["cup"]
    assert res["pairs"] == 3 and sorted(res["seeds"]) == [0, 1, 2]
    assert res["chamfer"][0] == pytest.approx(10.0) and res["chamfer"][1] == pytest.approx(0.0, abs=1e-9)
    assert res["floater_frac"][0] == pytest.approx(-20.0) and res["obs_chamfer"][0] == pytest.approx(10.0)
    assert "accuracy" not in res  # no row carries it
    assert "| cup | 3 | +10.0 +- 0.0 % |" in collect.paired_table(rows)


def test_held_out_rows_pair_by_their_warm_up_and_keep_a_variants_name(collect, tmp_path):
    """heldout.py's rows: ``noloop`` reads as ``no_loop``, a mode named after a hard.py variant keeps its name,
    the scene carries its rig, and rows that branched from one warm-up (their own ``started_from``) pair."""
    def row(mode, seed, chamfer, start):
        r = {"scene": "vase", "mode": mode, "seed": seed, "views": 10, "resolution": 512, "chamfer": chamfer,
             "obs_chamfer": chamfer / 2, "started_from": start}
        (tmp_path / f"h_x_vase_{mode}_{seed}.json").write_text(json.dumps(r))

    for seed, level in ((0, 1.0), (1, 2.0)):
        w = f"runs/abl/vase_s{seed}_v10_r512_warmup/checkpoints/ckpt.pt"
        row("coevo1k", seed, 0.9 * level, w)
        row("coevo1k_no_loop", seed, 1.0 * level, w)
        row("noloop", seed, 1.2 * level, w)
    rows = collect.load_rows([str(tmp_path)])
    assert {r["variant"] for r in rows} == {"coevo1k", "coevo1k_no_loop", "no_loop"}
    assert {r["scene"] for r in rows} == {"vase_v10_r512"}
    res = collect.paired(rows, loop="coevo1k", base="coevo1k_no_loop")["vase_v10_r512"]
    assert res["pairs"] == 2 and res["chamfer"][0] == pytest.approx(-10.0) and res["chamfer"][1] < 1e-9
    assert collect.paired(rows, loop="coevo1k_no_loop")["vase_v10_r512"]["chamfer"][0] == pytest.approx(100 / 1.2 - 100)


def test_the_suite_summary_reads_the_whole_truth_and_the_observed_region(collect, tmp_path):
    """Two scenes, one seed each: the summary lines give the mean Chamfer's change, the per-scene mean and the
    worst scene on the whole truth, and the same on the observed region, which can rank the scenes otherwise."""
    rows = []
    for sc, loop, base, loop_o, base_o in (("cup", 1.1, 1.0, 0.45, 0.5), ("torus", 0.08, 0.1, 0.08, 0.1)):
        rows += [{"scene": sc, "variant": "default", "seed": 0, "chamfer": loop, "obs_chamfer": loop_o},
                 {"scene": sc, "variant": "no_loop", "seed": 0, "chamfer": base, "obs_chamfer": base_o}]
    (tmp_path / "rows.json").write_text(json.dumps(rows))
    text = collect.table(collect.load_rows([str(tmp_path)]))
    whole = 100 * (np.mean([1.1, 0.08]) / np.mean([1.0, 0.1]) - 1)
    observed = 100 * (np.mean([0.45, 0.08]) / np.mean([0.5, 0.1]) - 1)
    assert f"({whole:+.1f} %); per scene {np.mean([10.0, -20.0]):+.1f} %; worst scene cup +10.0 %." in text
    assert (f"On the observed region, over 2 scenes: {np.mean([0.45, 0.08]):.4f} % against 0.3000 % "
            f"({observed:+.1f} %); per scene {np.mean([-10.0, -20.0]):+.1f} %; worst scene cup -10.0 %.") in text


def _suite_jobs(env: dict) -> list[str]:
    script = pathlib.Path(__file__).parents[2] / "lab" / "device" / "suite_jobs.sh"
    out = subprocess.run(["bash", str(script), "0 1", "t"], env={**os.environ, "SPLIT": "1", **env},
                         capture_output=True, text=True, check=True).stdout
    return out.splitlines()


def test_suite_jobs_orders_the_branches_by_variant_on_request():
    """BY_VARIANT=1 (lab/device/suite_jobs.sh): the same lines, the warm-ups first, then every scene's
    and seed's first variant before any second one, so a lease that ends early still leaves whole pairs."""
    env = {"SCENES": "torus chair", "VARIANTS": "default no_loop view_signs"}
    plain, by = _suite_jobs(env), _suite_jobs({**env, "BY_VARIANT": "1"})
    assert sorted(plain) == sorted(by) and len(by) == 4 + 12  # four warm-ups, twelve branches
    assert all("--warmup-only" in line for line in by[:4])
    variants = [line.split("--variants ")[1].split()[0] for line in by[4:]]
    assert variants == ["default"] * 4 + ["no_loop"] * 4 + ["view_signs"] * 4
    assert [line.split("--variants ")[1].split()[0] for line in plain[4:7]] == ["default", "no_loop", "view_signs"]


def test_suite_jobs_orders_the_held_out_branches_by_variant_too():
    """With HELDOUT=1 the held-out scenes' branch lines follow the same order: their warm-ups, then every held-out
    scene's and seed's first variant before any second one."""
    by = _suite_jobs({"SCENES": "", "HELDOUT": "1", "BY_VARIANT": "1", "VARIANTS": "no_geo_density default"})
    assert len(by) == 10 + 20 and all("--warmup-only" in line for line in by[:10])  # five scenes x two seeds
    variants = [line.split(" /root/stage/h_")[0].split()[-1] for line in by[10:]]
    assert variants == ["no_geo_density"] * 10 + ["default"] * 10
    assert all(line.startswith("while [ ! -f /root/stage/hw_t_") for line in by[10:])
