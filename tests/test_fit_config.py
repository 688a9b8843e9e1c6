# SPDX-License-Identifier: Apache-2.0
"""FitConfig validation: every field checked, bad values named by dotted path before any work."""

import dataclasses
import re

import numpy as np
import pytest

import wtopo
from wtopo import Camera, cli
from wtopo.fitting import DepthLoss, FitConfig, NormalFlip
from wtopo.fitting.config import REMOVED, InitSource, Range, RemovedFieldError, leaves
from wtopo.fitting.loop import FitRun
from wtopo.fitting.scene_kind import SceneKind
from wtopo.fitting.validate_config import check_leaf, validate_config
from wtopo.scene import Scene


def _with(path: str, value) -> FitConfig:
    cfg = FitConfig()
    *groups, name = path.split(".")
    obj = cfg
    for g in groups:
        obj = getattr(obj, g)
    setattr(obj, name, value)
    return cfg


def test_default_config_validates():
    """Accept the default FitConfig."""
    validate_config(FitConfig())


def test_toposurfel_public_config_validates():
    """Accept the public-TopoSurfel preset."""
    validate_config(FitConfig.toposurfel_public())


def test_dict_round_trip_validates():
    """Accept a config rebuilt from its JSON dict (enums as strings, background as a tuple)."""
    cfg = FitConfig.toposurfel_public()
    cfg.background = (0.1, 0.2, 0.3)
    validate_config(FitConfig.from_dict(cfg.to_dict()))


def test_every_leaf_field_has_a_check():
    """Give every numeric leaf field a range or choice in its metadata, and every leaf a check."""
    found = list(leaves(FitConfig()))
    assert len(found) > 40 and len({leaf.path for leaf in found}) == len(found)
    for leaf in found:
        if leaf.base in (int, float):
            assert isinstance(leaf.field.metadata.get("check"), (Range, tuple)), leaf.path
        check_leaf(leaf)  # raises TypeError for a type no check knows


def test_from_dict_names_unknown_paths_and_converts_enums():
    """Raise ValueError naming the dotted path of an unknown key; turn enum strings into members."""
    with pytest.raises(ValueError, match=re.escape("FitConfig has no field 'losses.nope'")):
        FitConfig.from_dict({"losses": {"nope": 1}})
    with pytest.raises(ValueError, match=re.escape("FitConfig has no field 'nope'")):
        FitConfig.from_dict({"nope": 1})
    with pytest.raises(ValueError, match="is a group"):
        FitConfig.from_dict({"losses": 1})
    with pytest.raises(ValueError, match=re.escape("mesh.normal_flip must be one of ['mesh', 'view', 'random'], "
                                                   "got 'mc'")):
        FitConfig.from_dict({"mesh": {"normal_flip": "mc"}})
    cfg = FitConfig.from_dict({"kind": "scene", "mesh": {"normal_flip": "view"}, "init": {"source": "points"},
                               "background": [0, 0, 1]})
    assert cfg.kind is SceneKind.SCENE and cfg.mesh.normal_flip is NormalFlip.VIEW
    assert cfg.init.source is InitSource.POINTS and cfg.background == (0, 0, 1)


def test_fit_config_has_at_most_62_leaf_fields():
    """Keep the configuration small: measured-and-rejected ideas and internal constants are not fields (60
    after the clean-up, plus ``preset`` and ``final.outline``: a masked object's mesh left where the fusion put
    it, for masks drawn wider or narrower than the object)."""
    assert len(list(leaves(FitConfig()))) <= 62
    assert not {leaf.path for leaf in leaves(FitConfig())} & set(REMOVED)


def test_a_removed_field_is_named_by_set_and_by_a_saved_config():
    """Raise RemovedFieldError naming the field (and every one of a saved config) with the value the fit now
    behaves as; a removed field is never silently ignored."""
    from wtopo.fitting.config import set_field

    with pytest.raises(RemovedFieldError, match=r"losses\.mask_halo \(measured and not kept; the fit behaves as "
                                                r"with False\)") as info:
        set_field(FitConfig(), "losses.mask_halo", True)
    assert info.value.paths == ["losses.mask_halo"] and isinstance(info.value, ValueError)
    with pytest.raises(RemovedFieldError, match=r"tsdf\.truncation_voxels \(now a fixed constant; the fit behaves "
                                                r"as with 4\.0\)"):
        set_field(FitConfig(), "tsdf.truncation_voxels", 3.0)
    saved = FitConfig().to_dict()
    saved["losses"].update(mask_halo=False, mesh_inset=0)
    saved["final"]["method"] = "tsdf"
    with pytest.raises(RemovedFieldError, match="older version") as info:
        FitConfig.from_dict(saved)
    assert sorted(info.value.paths) == ["final.method", "losses.mask_halo", "losses.mesh_inset"]
    with pytest.raises(RemovedFieldError, match=r"mesh\.silhouette_gain"):
        cli._apply_set(FitConfig(), "mesh.silhouette_gain=0.3")


BAD = [
    # (dotted path, value, error type)
    ("init.source", "mesh", ValueError),
    ("init.num_points", 0, ValueError),
    ("optim.means", float("nan"), ValueError),
    ("optim.quats", -1e-3, ValueError),
    ("optim.sh_dc", float("inf"), ValueError),
    ("optim.scales", "0.01", TypeError),
    ("optim.opacities", np.float32(0.05), TypeError),  # breaks the JSON config of checkpoints
    ("warmup.iterations", -3, ValueError),
    ("warmup.iterations", True, TypeError),
    ("warmup.iterations", 400.0, TypeError),
    ("warmup.iterations", np.int64(400), TypeError),
    ("tsdf.enabled", 1, TypeError),
    ("tsdf.resolution", 0, ValueError),
    ("tsdf.resolution", 4096, ValueError),
    ("tsdf.max_faces", 0, ValueError),
    ("tsdf.max_faces", 2.5, TypeError),
    ("coevolution.iterations", -1, ValueError),
    ("optim.means_decay_iterations", 0, ValueError),
    ("optim.means_decay_iterations", 2.5, TypeError),
    ("coevolution.enabled", "yes", TypeError),
    ("polish.iterations", -1, ValueError),
    ("polish.iterations", 2.5, TypeError),
    ("final.resolution", 7, ValueError),
    ("final.watertight", None, TypeError),
    ("densify.enabled", "auto", TypeError),
    ("densify.interval", 0, ValueError),
    ("densify.opacity_reset_fraction", -0.75, ValueError),
    ("losses.mask", float("nan"), ValueError),
    ("losses.mask", -0.5, ValueError),
    ("losses.depth_form", "log", ValueError),
    ("losses.depth_form", NormalFlip.MESH, ValueError),
    ("losses.depth_form", 1, TypeError),
    ("losses.mesh_depth_debias", "yes", TypeError),
    ("losses.mesh_depth_debias", 1, TypeError),
    ("mesh.resolution", 0, ValueError),
    ("mesh.samples_per_surfel", 3, ValueError),
    ("mesh.samples_per_surfel", 5.0, TypeError),
    ("mesh.normal_flip", "MESH", ValueError),
    ("mesh.normal_flip", DepthLoss.LOG_RATIO, ValueError),
    ("mesh.poisson_box", "cube", ValueError),
    ("mesh.sigma", -1.0, ValueError),
    ("runtime.device", "gpu", ValueError),
    ("runtime.device", "cuda:x", ValueError),
    ("runtime.device", 0, TypeError),
    ("runtime.seed", -1, ValueError),
    ("runtime.seed", 1.0, TypeError),
    ("runtime.image_scale", 2.0, ValueError),
    ("runtime.image_scale", 0.0, ValueError),
    ("runtime.stop_at", -5, ValueError),
    ("runtime.progress", None, TypeError),
    ("kind", "room", ValueError),
    ("preset", "fastest", ValueError),
    ("preset", 1, TypeError),
    ("kind", 1, TypeError),
    ("init.background_points", -1, ValueError),
    ("sh_degree", 4, ValueError),
    ("sh_degree", True, TypeError),
    ("background", (0.0, 0.0), ValueError),
    ("background", "black", TypeError),
    ("filter_sigma", 0.0, ValueError),
    ("filter_sigma", -0.35, ValueError),
]


@pytest.mark.parametrize("path, value, error", BAD, ids=[f"{p}={v!r}" for p, v, _ in BAD])
def test_bad_value_names_field_and_value(path, value, error):
    """Raise the right error type naming the dotted path and the bad value."""
    with pytest.raises(error, match=re.escape(f"FitConfig.{path} must be ")) as info:
        validate_config(_with(path, value))
    assert f"got {value!r}" in str(info.value)


def test_bad_values_cover_every_group():
    """Exercise bad values in every stage group and at the top level (at least 15 fields)."""
    paths = {p for p, _, _ in BAD}
    assert len(paths) >= 15
    groups = {f.name for f in dataclasses.fields(FitConfig)}
    assert groups <= {p.split(".")[0] for p in paths}


def test_background_component_is_named_by_index():
    """Name the offending background component, e.g. ``background[1]``."""
    msg = "FitConfig.background[1] must be a finite number in [0, 1], got 1.5"
    with pytest.raises(ValueError, match=re.escape(msg)):
        validate_config(_with("background", (0.0, 1.5, 0.0)))


@pytest.mark.parametrize("path, value", [
    ("optim.means", 1),  # an int is a number
    ("filter_sigma", 1),
    ("losses.depth_form", "log1p_abs"),
    ("losses.depth_form", DepthLoss.LOG1P_ABS),
    ("mesh.normal_flip", "random"),
    ("mesh.normal_flip", NormalFlip.VIEW),
    ("runtime.device", "cuda:1"),
    ("runtime.device", "cuda"),
    ("runtime.device", "cpu"),
    ("densify.enabled", False),
    ("losses.mask", 0.0),
    ("sh_degree", 0),
    ("background", [1.0, 1.0, 1.0]),
    ("runtime.stop_at", 20),
])
def test_good_values_are_accepted(path, value):
    """Accept ints for floats, enum members and their strings, optional fields and edge values."""
    validate_config(_with(path, value))


def test_means_final_above_means_is_rejected():
    """Reject a means learning rate that would grow instead of decay; accept a 0 on either side."""
    cfg = _with("optim.means_final", 1e-2)
    with pytest.raises(ValueError, match=r"FitConfig\.optim\.means_final must be <= FitConfig\.optim\.means"):
        validate_config(cfg)
    cfg.optim.means = 0.0  # a frozen means: the schedule is off
    validate_config(cfg)


@pytest.mark.parametrize("group", ["optim", "runtime"])
def test_wrong_group_type_is_rejected(group):
    """Reject a stage group replaced by a dict or None, naming the group."""
    cfg = FitConfig()
    setattr(cfg, group, {"means": 1e-3})
    with pytest.raises(TypeError, match=rf"FitConfig\.{group} must be a \w+Config"):
        validate_config(cfg)


def test_non_fitconfig_is_rejected():
    """Reject an object that is not a FitConfig."""
    with pytest.raises(TypeError, match="FitConfig"):
        validate_config({"warmup": {"iterations": 3}})


def _tiny_scene() -> Scene:
    cams = [Camera.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0], [0, 0, 1], fov_x=0.8, width=24, height=20)
            for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    return Scene(cams, np.zeros((6, 20, 24, 3), np.float32))


def test_fit_rejects_a_bad_config_before_any_work(monkeypatch):
    """Raise from wtopo.fitting before the scene is normalised or the fit engine is built."""
    def unreachable(*args, **kwargs):
        raise AssertionError("fit started work with an invalid config")

    monkeypatch.setattr(FitRun, "__init__", unreachable)
    monkeypatch.setattr(Scene, "normalization", unreachable)
    monkeypatch.setattr(Scene, "normalized", unreachable)
    scene = _tiny_scene()
    with pytest.raises(ValueError, match=re.escape("FitConfig.warmup.iterations must be an int >= 0 or None, got -3")):
        wtopo.fit(scene, _with("warmup.iterations", -3), progress=False)
    bad_grid = "FitConfig.tsdf.resolution must be an int in [8, 2048] or None, got True"
    with pytest.raises(TypeError, match=re.escape(bad_grid)):
        wtopo.fit(scene, _with("tsdf.resolution", True), progress=False)


def test_cli_reports_a_bad_config_without_a_traceback(monkeypatch, capsys, tmp_path):
    """Print ``wtopo fit: error: <message>`` and exit 2 before loading the scene."""

    def unreachable(*args, **kwargs):
        raise AssertionError("the CLI loaded the scene with an invalid config")

    monkeypatch.setattr(cli, "_load", unreachable)
    code = cli.main(["fit", "bunny", "--out", str(tmp_path / "run"), "--device", "gpu"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("wtopo fit: error: FitConfig.runtime.device must be ") and "'gpu'" in err
    assert cli.main(["fit", "bunny", "--out", str(tmp_path / "run"), "--iterations", "-4"]) == 2
    assert "FitConfig.warmup.iterations must be an int >= 0 or None, got -2" in capsys.readouterr().err


def test_default_schedule_fractions_give_the_cpu_iterations():
    """Place the default schedule's events at the CPU budget's iterations (warm-up 800, co-evolution 800)."""
    from wtopo.fitting import _strategy as strategy
    from wtopo.fitting import objective
    from wtopo.fitting.config import stage_iteration

    cfg = FitConfig()
    assert stage_iteration(strategy.DENSIFY_START, 800) == 200
    assert stage_iteration(cfg.densify.opacity_reset_fraction, 800) == 600
    assert stage_iteration(objective._NORMAL_START, 800) == 400
    assert stage_iteration(objective._DISTORTION_START, 800) == 400
    assert stage_iteration(strategy._CORRESPONDENCE_FRACTION, 800) == 400
    assert stage_iteration(0.25, 30) == 8  # halves round up: 7.5 -> 8
