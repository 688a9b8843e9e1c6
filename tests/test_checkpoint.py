# SPDX-License-Identifier: Apache-2.0
"""Atomic, validated, resumable checkpoints (design/stability.md, "Not losing work")."""

import random

import numpy as np
import pytest
import torch

from wtopo.fitting.checkpoint import (
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from wtopo.fitting.surfels import Surfels


def _surfels(n=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    s = Surfels.from_points(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g),
                            scales=torch.full((n,), 0.01), generator=g)
    opt = s.optimizer({k: 1e-2 for k in s.params})
    loss = sum((p ** 2).sum() for p in s.params.values())
    loss.backward()
    opt.step()
    return s, opt


def _state(s, opt, h="abc"):
    return {"surfels": s.state_dict(), "optimizer": opt.state_dict(), "config_hash": h, "rng": rng_state()}


def test_roundtrip_restores_parameters_optimizer_and_versions(tmp_path):
    """Save and load: parameters, Adam moments, step and versions come back."""
    s, opt = _surfels()
    save_checkpoint(tmp_path, 7, _state(s, opt))
    st = load_checkpoint(tmp_path, config_hash="abc")
    assert st["step"] == 7 and {"wtopo", "warp", "torch"} <= set(st["versions"])
    s2 = Surfels.from_state_dict(st["surfels"])
    opt2 = s2.optimizer({k: 1e-2 for k in s2.params})
    opt2.load_state_dict(st["optimizer"])
    for k in s.params:
        torch.testing.assert_close(s2.params[k], s.params[k], rtol=0, atol=0)
        torch.testing.assert_close(opt2.state[s2.params[k]]["exp_avg"], opt.state[s.params[k]]["exp_avg"])


def test_keeps_last_two_and_leaves_no_temporary_files(tmp_path):
    """Keep only the newest K checkpoints; no temporary file survives a save."""
    s, opt = _surfels()
    for step in (1, 2, 3, 4):
        save_checkpoint(tmp_path, step, _state(s, opt), keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_00000003.pt", "ckpt_00000004.pt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_refuses_to_save_non_finite_state(tmp_path):
    """Never write NaN parameters over a good checkpoint."""
    s, opt = _surfels()
    save_checkpoint(tmp_path, 1, _state(s, opt))
    with torch.no_grad():
        s.params["means"][0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        save_checkpoint(tmp_path, 2, _state(s, opt))
    assert load_checkpoint(tmp_path)["step"] == 1


def test_corrupt_newest_falls_back_to_previous(tmp_path):
    """A truncated newest checkpoint is skipped with a warning; the previous one loads."""
    s, opt = _surfels()
    save_checkpoint(tmp_path, 1, _state(s, opt))
    p2 = save_checkpoint(tmp_path, 2, _state(s, opt))
    p2.write_bytes(p2.read_bytes()[:100])
    with pytest.warns(RuntimeWarning, match="unreadable"):
        st = load_checkpoint(tmp_path)
    assert st["step"] == 1


def test_inconsistent_counts_fall_back(tmp_path):
    """A checkpoint whose tensors disagree on the surfel count is rejected."""
    s, opt = _surfels()
    save_checkpoint(tmp_path, 1, _state(s, opt))
    bad = _state(s, opt)
    bad["surfels"]["params"]["means"] = bad["surfels"]["params"]["means"][:3]
    save_checkpoint(tmp_path, 2, bad)
    with pytest.warns(RuntimeWarning, match="disagree"):
        assert load_checkpoint(tmp_path)["step"] == 1


def test_other_configuration_is_not_resumed(tmp_path):
    """Raise CheckpointError when every checkpoint has another config hash, or none exists."""
    s, opt = _surfels()
    save_checkpoint(tmp_path, 1, _state(s, opt, h="other"))
    with pytest.raises(CheckpointError, match="config hash"):
        load_checkpoint(tmp_path, config_hash="abc")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "missing")


def test_keep_must_be_at_least_two(tmp_path):
    """Reject keep < 2 (the fallback needs a previous checkpoint)."""
    s, opt = _surfels()
    with pytest.raises(ValueError, match="keep"):
        save_checkpoint(tmp_path, 1, _state(s, opt), keep=1)


def test_rng_state_roundtrip():
    """Restoring the RNG states replays torch, NumPy and Python random streams."""
    st = rng_state()
    a = (torch.rand(3), np.random.rand(3), random.random())
    set_rng_state(st)
    b = (torch.rand(3), np.random.rand(3), random.random())
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=0)
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2] == b[2]
