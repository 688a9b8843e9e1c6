# SPDX-License-Identifier: Apache-2.0
"""Quality presets: what each gives the plan, that set fields win over it, and how it reaches the CLI."""

import json

import pytest
import torch

from wtopo import cli, scenes
from wtopo.fitting import FitConfig, Preset, make_plan, plan_defaults
from wtopo.fitting.presets import budget, expected_seconds

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def bunny():
    return scenes.load("bunny").normalized()


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_presets_order_iterations_and_time(device):
    """Fast < balanced < best in iterations and in expected time on the same views, on each kind of device."""
    its = [sum(budget(p, device).iterations) for p in ("fast", "balanced", "best")]
    assert its == sorted(its) and len(set(its)) == 3
    t = [expected_seconds(p, device, sum(budget(p, device).iterations), 128 * 128) for p in Preset]
    assert t == sorted(t) and all(x > 0 for x in t)
    assert expected_seconds("balanced", device, 2000, 128 * 128) > expected_seconds("balanced", device, 1000, 128 * 128)
    assert budget(Preset.FAST, device) == budget("fast", torch.device(device))


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_expected_time_grows_with_covered_pixels_proxy_builds_and_the_stereo(device):
    """The time model: more covered pixels, more proxy builds and (on a CPU, where it runs long) the stereo each
    add time; nothing else does."""
    base = expected_seconds("balanced", device, 1000, 10_000)
    assert expected_seconds("balanced", device, 1000, 40_000) > base
    assert expected_seconds("balanced", device, 1000, 10_000, proxy_builds=500) > base
    stereo = expected_seconds("balanced", device, 1000, 10_000, stereo=True)
    assert stereo > base if device == "cpu" else stereo == base
    assert expected_seconds("balanced", device, 1000, 10_000, proxy_builds=-3) == base


def test_plan_times_the_covered_pixels_and_the_proxy_builds(bunny):
    """The plan's expected time counts the mask's share of each view and one proxy build per ``mesh_every``
    co-evolution iterations; without its loop, none."""
    plan = make_plan(bunny, FitConfig(), CPU)
    b = budget("balanced", CPU)
    covered = float(bunny.masks.float().mean()) * (128 * plan.image_scale) ** 2
    builds = -(-plan.coevolution_iterations // b.mesh_every)
    n_it = plan.warmup_iterations + plan.coevolution_iterations + plan.polish_iterations
    assert 0.05 < covered / (128 * plan.image_scale) ** 2 < 0.5
    # the plan reads the training views' masks; the whole scene's differ from them by a few pixels a view
    assert plan.expected_seconds == pytest.approx(
        expected_seconds("balanced", CPU, n_it, covered, proxy_builds=builds), abs=1.0)
    cfg = FitConfig()
    cfg.coevolution.enabled = False
    off = make_plan(bunny, cfg, CPU)
    n_off = off.warmup_iterations + off.coevolution_iterations + off.polish_iterations
    assert off.expected_seconds == pytest.approx(expected_seconds("balanced", CPU, n_off, covered), abs=1.0)
    assert ", 0 proxy builds," in off.reasons["expected_seconds"] and not off.mesh_loop
    cfg = FitConfig()
    cfg.losses.mesh_depth = cfg.losses.mesh_normal = 0.0  # the loop runs, but builds no proxy
    flat = make_plan(bunny, cfg, CPU)
    assert flat.mesh_loop and flat.expected_seconds == pytest.approx(
        expected_seconds("balanced", CPU, n_it, covered), abs=1.0)
    cfg = FitConfig()
    cfg.init.source = "mvs"  # the stereo's initial surfels, on an object too
    mvs = make_plan(bunny, cfg, CPU)
    assert ", the stereo," in mvs.reasons["expected_seconds"] and mvs.expected_seconds == pytest.approx(
        expected_seconds("balanced", CPU, n_it, covered, proxy_builds=builds, stereo=True), abs=1.0)


def test_unknown_preset_is_named():
    with pytest.raises(ValueError, match="preset must be one of \\['fast', 'balanced', 'best'\\], got 'quick'"):
        budget("quick", "cpu")


def test_plan_takes_the_presets_budgets(bunny):
    """Each preset's iterations, image cap and grids reach the plan, with the preset and its expected time."""
    plans = {}
    for p in Preset:
        cfg = FitConfig()
        cfg.preset = p
        plans[p] = make_plan(bunny, cfg, CPU)
        b = budget(p, CPU)
        assert (plans[p].warmup_iterations, plans[p].coevolution_iterations) == b.iterations
        assert b.proxy_grid[0] <= plans[p].proxy_resolution <= b.proxy_grid[1]
        assert b.final_grid[0] <= plans[p].final_resolution <= b.final_grid[1]
        assert plans[p].image_scale == min(1.0, b.max_side / 128)
        assert plans[p].preset is p and plans[p].expected_seconds > 0
        assert f"preset {p.value}" in str(plans[p]).splitlines()[0]
        d = json.loads(json.dumps(plans[p].to_dict()))
        assert d["preset"]["value"] == p.value and d["expected_seconds"]["value"] == plans[p].expected_seconds
    assert FitConfig().preset is Preset.BALANCED
    assert plans[Preset.FAST].expected_seconds < plans[Preset.BALANCED].expected_seconds \
        < plans[Preset.BEST].expected_seconds
    # shorter warm-ups keep about as many density steps
    assert plans[Preset.FAST].densify_interval < plans[Preset.BEST].densify_interval == 100


def test_set_fields_win_over_the_preset(bunny):
    cfg = FitConfig()
    cfg.preset = Preset.FAST
    cfg.warmup.iterations = 321
    cfg.mesh.resolution = 80
    cfg.densify.interval = 7
    plan = make_plan(bunny, cfg, CPU)
    assert plan.warmup_iterations == 321 and plan.proxy_resolution == 80 and plan.densify_interval == 7
    assert {"warmup_iterations", "proxy_resolution", "densify_interval"} <= plan.overrides
    assert plan.coevolution_iterations == budget("fast", CPU).iterations[1]  # the rest is still the preset's


def test_cli_preset_then_set():
    parse = cli.build_parser().parse_args
    assert cli._config(parse(["fit", "bunny", "--out", "x"])).preset is Preset.BALANCED
    assert cli._config(parse(["fit", "bunny", "--out", "x", "--preset", "fast"])).preset is Preset.FAST
    cfg = cli._config(parse(["fit", "bunny", "--out", "x", "--preset", "fast", "--set", "preset=best",
                             "--set", "coevolution.iterations=9"]))
    assert cfg.preset is Preset.BEST and cfg.coevolution.iterations == 9
    with pytest.raises(SystemExit):
        parse(["fit", "bunny", "--out", "x", "--preset", "quick"])


def test_chunk_defaults_follow_the_preset():
    assert plan_defaults("cpu", "fast").iterations == budget("fast", "cpu").iterations
    assert plan_defaults("cuda", "best").iterations == budget("best", "cuda").iterations
    assert plan_defaults("cpu").iterations == budget("balanced", "cpu").iterations
