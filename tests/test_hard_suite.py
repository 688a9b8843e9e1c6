"""The hard-scene suite's runner (``benchmarks/hard.py``): what it records for a fit."""

import pytest
import trimesh

import benchmarks.hard as hard  # the README's test command runs from the repository root
from wtopo import scenes


def test_an_interrupted_fit_stops_the_suite_unrecorded(tmp_path):
    """A fit stopped before its last iteration (a signal; here ``runtime.stop_at``) is no result: the
    runner raises instead of measuring its mesh, and the suite's main loop stops on it."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    scene = scenes.from_mesh(sphere, n_views=8, resolution=24, name="tiny")
    with pytest.raises(hard.FitInterrupted, match="interrupted"):
        hard.run_one("tiny", "default", (scene, sphere, None), str(tmp_path), ["runtime.stop_at=3"])
    assert (tmp_path / "tiny_default").is_dir(), "the fit ran (and checkpointed) before it stopped"
