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


def test_set_reaches_any_field_and_config_file_round_trips(tmp_path):
    """--set PATH=VALUE sets nested fields with JSON values and enums; --config starts from a saved config."""
    import json

    from wtopo.fitting import FitConfig
    from wtopo.fitting.config import NormalFlip

    args = cli.build_parser().parse_args([
        "fit", "bunny", "--out", "x", "--set", "losses.mask=0.5", "--set", "final.method=proxy",
        "--set", "mesh.normal_flip=view", "--set", "background=[1, 1, 1]", "--set", "densify.enabled=false",
        "--set", "filter_sigma=0.5"])
    cfg = cli._config(args)
    assert cfg.losses.mask == 0.5 and cfg.final.method == "proxy" and cfg.mesh.normal_flip is NormalFlip.VIEW
    assert cfg.background == (1, 1, 1) and cfg.densify.enabled is False and cfg.filter_sigma == 0.5
    saved = FitConfig()
    saved.warmup.iterations = 7
    path = tmp_path / "config.json"
    path.write_text(json.dumps(saved.to_dict()))
    cfg = cli._config(cli.build_parser().parse_args(["fit", "bunny", "--out", "x", "--config", str(path),
                                                     "--set", "coevolution.iterations=3"]))
    assert (cfg.warmup.iterations, cfg.coevolution.iterations) == (7, 3)


def test_bad_set_and_config_are_reported(tmp_path, capsys, monkeypatch):
    """Unknown paths, groups, bad enum values and unreadable config files end in a message and exit 2."""
    import pytest

    def unreachable(*a, **k):
        raise AssertionError("the CLI loaded the scene with a bad configuration")

    monkeypatch.setattr(cli, "_load", unreachable)
    out = str(tmp_path / "run")
    for extra, words in ((["--set", "losses.nope=1"], "losses.nope"), (["--set", "losses=1"], "group"),
                         (["--set", "mesh.normal_flip=sideways"], "normal_flip"), (["--set", "noequals"], "PATH=VALUE"),
                         (["--config", str(tmp_path / "missing.json")], "missing.json"),
                         (["--set", "losses.mask=-1"], "losses.mask")):
        assert cli.main(["fit", "bunny", "--out", out, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert "wtopo fit: error:" in err and words in err, (extra, err)
    bad = tmp_path / "bad.json"
    bad.write_text('{"warmup": {"iterationz": 3}}')
    assert cli.main(["fit", "bunny", "--out", out, "--config", str(bad)]) == 2
    assert "iterationz" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["fit", "bunny", "--out", out, "--set"])
