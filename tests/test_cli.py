# SPDX-License-Identifier: Apache-2.0
"""The ``wtopo`` command: flags reach FitConfig, built-in scenes are listed."""

from wtopo import cli


def test_fit_flags_override_the_config():
    """Map every fit flag onto its FitConfig field, leaving the rest at the defaults."""
    args = cli.build_parser().parse_args([
        "fit", "bunny", "--out", "x", "--iterations", "31", "--device", "cpu", "--seed", "7",
        "--max-surfels", "123", "--usd-every", "0", "--normal-flip", "view", "--samples-per-surfel", "1",
        "--poisson-resolution", "48", "--no-mesh-loop"])
    cfg = cli._config(args)
    assert (cfg.warmup.iterations, cfg.coevolution.iterations) == (15, 16)
    assert (cfg.runtime.device, cfg.runtime.seed, cfg.runtime.max_surfels, cfg.runtime.usd_every) == ("cpu", 7, 123, 0)
    assert (cfg.mesh.normal_flip, cfg.mesh.samples_per_surfel, cfg.mesh.resolution) == ("view", 1, 48)
    assert cfg.coevolution.enabled is False
    later = cli._config(cli.build_parser().parse_args(["fit", "bunny", "--out", "x", "--warmup", "5"]))
    assert later.warmup.iterations == 5 and later.coevolution.enabled is True


def test_scenes_lists_the_built_ins(capsys):
    """Print one built-in scene name per line."""
    assert cli.main(["scenes"]) == 0
    out = capsys.readouterr().out.split()
    assert {"bunny", "bunny_room", "sphere"} <= set(out)
