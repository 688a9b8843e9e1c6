# SPDX-License-Identifier: Apache-2.0
"""The ``wtopo`` command: flags reach FitConfig, built-in scenes are listed."""

from wtopo import cli


def test_fit_flags_override_the_config():
    """Map every fit flag onto its FitConfig field, leaving the rest at the defaults."""
    args = cli.build_parser().parse_args([
        "fit", "bunny", "--out", "x", "--iterations", "31", "--device", "cpu", "--seed", "7",
        "--max-surfels", "123", "--usd-every", "0", "--normal-flip", "view", "--samples-per-surfel", "1",
        "--proxy-resolution", "48", "--downscale", "4", "--no-mesh-loop"])
    cfg = cli._config(args)
    assert (cfg.warmup.iterations, cfg.coevolution.iterations) == (15, 16)
    assert (cfg.runtime.device, cfg.runtime.seed, cfg.runtime.max_surfels, cfg.runtime.usd_every) == ("cpu", 7, 123, 0)
    assert (cfg.mesh.normal_flip, cfg.mesh.samples_per_surfel, cfg.mesh.resolution) == ("view", 1, 48)
    assert cfg.runtime.image_scale == 0.25
    assert cfg.coevolution.enabled is False
    later = cli._config(cli.build_parser().parse_args(["fit", "bunny", "--out", "x", "--warmup", "5"]))
    assert later.warmup.iterations == 5 and later.coevolution.enabled is None  # the plan decides
    assert later.runtime.image_scale is None  # without --downscale the plan decides


def test_each_flag_in_the_table_sets_only_its_field():
    """Change exactly the FitConfig field a table flag names, nothing else (the flag says what it sets)."""
    import dataclasses

    from wtopo.fitting import FitConfig

    def leaves(cfg, prefix=""):
        out = {}
        for f in dataclasses.fields(cfg):
            v = getattr(cfg, f.name)
            out.update(leaves(v, prefix + f.name + ".") if dataclasses.is_dataclass(v) else {prefix + f.name: v})
        return out

    base = leaves(FitConfig())
    assert len(cli._OVERRIDES) >= 9
    for arg, section, name in cli._OVERRIDES:
        value = {"device": "cpu", "normal_flip": "random"}.get(arg, 5 if arg != "samples_per_surfel" else 1)
        flag = "--" + arg.replace("_", "-")
        cfg = cli._config(cli.build_parser().parse_args(["fit", "bunny", "--out", "x", flag, str(value)]))
        changed = {k for k, v in leaves(cfg).items() if v != base[k]}
        assert changed == {f"{section}.{name}"} and getattr(getattr(cfg, section), name) == value, (flag, changed)


def test_headless_flag_is_gone():
    """Reject the removed no-op --headless flag as an unknown argument."""
    import pytest

    with pytest.raises(SystemExit) as e:
        cli.build_parser().parse_args(["fit", "bunny", "--out", "x", "--headless"])
    assert e.value.code == 2


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
        "fit", "bunny", "--out", "x", "--set", "losses.mask=0.5", "--set", "mesh.sigma=0.5",
        "--set", "mesh.normal_flip=view", "--set", "background=[1, 1, 1]", "--set", "densify.enabled=false",
        "--set", "filter_sigma=0.5"])
    cfg = cli._config(args)
    assert cfg.losses.mask == 0.5 and cfg.mesh.sigma == 0.5 and cfg.mesh.normal_flip is NormalFlip.VIEW
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


def _one_error_line(err: str, command: str = "fit") -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"wtopo {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


def test_user_errors_are_one_line_with_exit_2(tmp_path, capsys):
    """Report a missing path, a truncated image and a bad --set value as one stderr line, exit 2."""
    import numpy as np
    from test_loader_robustness import _nerfstudio, _truncated_jpeg

    out = str(tmp_path / "run")
    missing = str(tmp_path / "no_such_dataset")
    assert cli.main(["fit", missing, "--out", out]) == 2
    assert missing in _one_error_line(capsys.readouterr().err)

    data = tmp_path / "capture"
    data.mkdir()
    _nerfstudio(str(data), 3, jpeg=True)
    bad = str(data / "images" / "frame_001.jpg")
    _truncated_jpeg(bad, np.random.default_rng(0))
    assert cli.main(["fit", str(data), "--out", out, "--iterations", "2"]) == 2
    assert f"cannot read image {bad}" in _one_error_line(capsys.readouterr().err)

    assert cli.main(["fit", "bunny", "--out", out, "--set", "losses.mask=-1"]) == 2
    assert "losses.mask" in _one_error_line(capsys.readouterr().err)
    assert cli.main(["fit", "bunny", "--out", out, "--downscale", "0.5"]) == 2
    assert "--downscale must be a finite number >= 1, got 0.5" in _one_error_line(capsys.readouterr().err)
    assert cli.main(["export", str(tmp_path / "no_run"), str(tmp_path / "m.obj")]) == 2
    _one_error_line(capsys.readouterr().err, "export")
    assert not (tmp_path / "run").exists()  # nothing ran


def test_usage_errors_are_one_line(capsys):
    """Report a flag argparse rejects as one line naming the subcommand, exit 2."""
    import pytest

    with pytest.raises(SystemExit) as e:
        cli.main(["fit", "bunny", "--out", "x", "--iterations", "many"])
    assert e.value.code == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "--iterations" in line and "wtopo fit --help" in line


def test_programming_errors_keep_their_traceback(tmp_path, monkeypatch, capsys):
    """Let errors that are not user errors propagate; --traceback re-raises user errors too."""
    import pytest

    def broken(scene, **kwargs):
        raise KeyError("a bug")

    monkeypatch.setattr(cli, "_load", broken)
    with pytest.raises(KeyError, match="a bug"):
        cli.main(["fit", "bunny", "--out", str(tmp_path / "run")])
    monkeypatch.undo()
    with pytest.raises(FileNotFoundError, match="no_such_dataset"):
        cli.main(["fit", str(tmp_path / "no_such_dataset"), "--out", str(tmp_path / "run"), "--traceback"])
    assert capsys.readouterr().err == ""


def test_loader_warnings_are_one_line(tmp_path, monkeypatch, capsys):
    """Print the loader's skipped-frames warning as one 'wtopo fit: warning:' line before the fit starts."""
    import types

    from test_loader_robustness import _nerfstudio

    import wtopo.fitting

    seen = {}

    def fake_fit(scene, cfg, **kw):
        seen["n"] = len(scene)
        return types.SimpleNamespace(report={"status": "completed"})

    monkeypatch.setattr(wtopo.fitting, "fit", fake_fit)
    _nerfstudio(str(tmp_path), 4, missing=(2,))
    assert cli.main(["fit", str(tmp_path), "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert seen["n"] == 3
    assert err == [f"wtopo fit: warning: 1 of 4 images listed in {tmp_path / 'transforms.json'} are missing and were "
                   "skipped: images/frame_002.png"], err


_WARP_CPU_SCRIPT = """
import wtopo
import wtopo.ops
import warp as wp


@wp.kernel
def fill(a: wp.array(dtype=float)):
    a[wp.tid()] = 2.0


a = wp.zeros(8, dtype=float, device="cpu")
wp.launch(fill, dim=8, inputs=[a], device="cpu")
print(float(a.numpy().sum()))
"""


def test_no_cuda_probe_warning_on_import_and_cpu_launch(tmp_path):
    """Import wtopo and launch a CPU kernel in a fresh process without a 'Warp CUDA warning' line."""
    import subprocess
    import sys

    import warp as wp

    script = tmp_path / "cpu_launch.py"
    script.write_text(_WARP_CPU_SCRIPT)
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "16.0"
    assert "CUDA warning" not in run.stderr, run.stderr
    if wp.get_cuda_device_count() == 0:  # the same process with plain Warp does print it: the filter is what removed it
        plain = subprocess.run([sys.executable, "-c", "import warp; warp.init()"], capture_output=True, text=True,
                               timeout=300)
        assert "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver" in plain.stderr, plain.stderr


def test_warp_init_filter_keeps_other_lines(capfd):
    """Drop only the no-driver probe line from what Warp's init writes to fd 2; other lines and errors pass."""
    import os

    import pytest

    import wtopo

    other = "Warp CUDA warning: Unable to determine CUDA driver version"

    def noisy_init():
        os.write(2, f"{wtopo._CUDA_PROBE_LINE}\n{other}\n".encode())

    wtopo._init_warp(noisy_init)
    err = capfd.readouterr().err
    assert other in err and "Could not find or load" not in err, err

    def failing_init():
        os.write(2, f"{wtopo._CUDA_PROBE_LINE}\nnative error detail\n".encode())
        raise RuntimeError("init failed")

    with pytest.raises(RuntimeError, match="init failed"):
        wtopo._init_warp(failing_init)
    os.write(2, b"after\n")  # fd 2 is restored
    err = capfd.readouterr().err
    assert err == "native error detail\nafter\n", err
