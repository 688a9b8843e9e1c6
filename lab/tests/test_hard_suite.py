"""The hard-scene suite's runner (``lab/hard.py``): what it records for a fit."""

import lab.hard as hard  # the README's test command runs from the repository root
import pytest
import trimesh

from wtopo import scenes


def test_an_interrupted_fit_stops_the_suite_unrecorded(tmp_path):
    """A fit stopped before its last iteration (a signal; here ``runtime.stop_at``) is no result: the
    runner raises instead of measuring its mesh, and the suite's main loop stops on it."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    scene = scenes.from_mesh(sphere, n_views=8, resolution=24, name="tiny")
    with pytest.raises(hard.FitInterrupted, match="interrupted"):
        hard.run_one("tiny", "default", (scene, sphere, None), str(tmp_path), ["runtime.stop_at=3"])
    assert (tmp_path / "tiny_default").is_dir(), "the fit ran (and checkpointed) before it stopped"


@pytest.mark.parametrize("name, genus", [("table", 2), ("stool", 3), ("shelf", 3), ("vase", 0), ("pretzel", 2)])
def test_held_out_scenes_are_closed_with_their_loops(name, genus):
    """``lab/heldout.py``'s truth meshes: one closed, consistently wound part each, with the
    loops its docstring names (the table's two stretchers, the stool's three legs under a ring, the
    shelf's three openings), inside the grid it is built on."""
    import lab.hard_scenes as hs
    import lab.heldout as th

    sdf, lower, upper = th.SCENES[name]
    mesh = hs.sdf_mesh(sdf, lower, upper, 0.012)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1
    assert 1 - mesh.euler_number // 2 == genus
    assert (mesh.bounds[0] > lower).all() and (mesh.bounds[1] < upper).all()


def test_held_out_thin_scene_names_are_checked():
    import lab.heldout as th

    with pytest.raises(SystemExit):
        th.main(["--scene", "lamp", "0", "on", "out.json"])
    with pytest.raises(SystemExit):
        th.main(["--scene", "stool", "0", "maybe", "out.json"])


def test_the_suites_variants_change_only_what_acts_after_the_warmup():
    """lab/hard.py's variants may branch from the default's warm-up (``--paired``)."""
    import importlib.util
    import pathlib

    from wtopo.fitting.checkpointing import warmup_differences

    path = pathlib.Path(__file__).parents[1] / "hard.py"
    spec = importlib.util.spec_from_file_location("hard_bench", path)
    hard = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hard)
    gpu = ["runtime.seed=3", "warmup.iterations=3000", "coevolution.iterations=2000",
           "optim.means_decay_iterations=4000"]  # the CUDA plan's
    base = hard._config("default", gpu).to_dict()
    assert len(hard.VARIANTS) >= 8
    for v in hard.VARIANTS:
        assert warmup_differences(base, hard._config(v, gpu).to_dict()) == [], v
    base = hard._config("default", ["runtime.seed=3"]).to_dict()
    assert warmup_differences(base, hard._config("default", ["runtime.seed=4"]).to_dict()) == ["runtime.seed"]
    assert warmup_differences(base, hard._config("default", ["runtime.seed=3", "warmup.iterations=7"]).to_dict()) == [
        "warmup.iterations"]
