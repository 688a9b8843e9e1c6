# SPDX-License-Identifier: Apache-2.0
"""The fit's Adam (:mod:`wtopo.fitting.adam`) against ``torch.optim.Adam``: the same parameters after many
steps with changing rates and gradients that skip a step, and state dicts that load both ways."""

from __future__ import annotations

import pytest
import torch

from wtopo.fitting.adam import Adam


def _groups(seed=0):
    g = torch.Generator().manual_seed(seed)
    return [{"params": [torch.randn(40, 3, generator=g).requires_grad_()], "lr": 1e-2, "name": "a"},
            {"params": [torch.randn(40, generator=g).requires_grad_()], "lr": 5e-2, "name": "b"}]


def _run(opt, groups, steps, seed=1, start=0):
    g = torch.Generator().manual_seed(seed)
    for k in range(start, start + steps):
        for grp in groups:
            p = grp["params"][0]
            if k % 7 == 3 and grp["name"] == "b":  # a step without a gradient for one group
                p.grad = None
                continue
            p.grad = torch.randn(p.shape, generator=g) * (1 + k % 5)
        opt.param_groups[0]["lr"] = 1e-2 * 0.97 ** k  # a decaying rate, as the means'
        opt.step()
        opt.zero_grad(set_to_none=True)


def test_matches_torch_adam():
    ours, theirs = _groups(), _groups()
    start = [g["params"][0].detach().clone() for g in ours]
    a = Adam(ours, eps=1e-15)
    b = torch.optim.Adam(theirs, lr=0.0, eps=1e-15)
    _run(a, ours, 60)
    _run(b, theirs, 60)
    for x, y, x0 in zip(ours, theirs, start):
        assert not torch.equal(x["params"][0], x0)  # the steps moved it
        torch.testing.assert_close(x["params"][0], y["params"][0], rtol=0, atol=1e-6)
        sa, sb = a.state[x["params"][0]], b.state[y["params"][0]]
        assert float(sa["step"]) == float(sb["step"]) and float(sa["step"]) > 0
        torch.testing.assert_close(sa["exp_avg_sq"], sb["exp_avg_sq"], rtol=1e-6, atol=0)


@pytest.mark.parametrize("direction", ["torch_to_ours", "ours_to_torch"])
def test_state_dicts_load_both_ways(direction):
    """A checkpoint's optimiser state from either class resumes in the other to the same parameters."""
    src_groups, ref_groups = _groups(), _groups()
    src = torch.optim.Adam(src_groups, lr=0.0, eps=1e-15) if direction == "torch_to_ours" else Adam(src_groups,
                                                                                                   eps=1e-15)
    ref = Adam(ref_groups, eps=1e-15)
    _run(src, src_groups, 20)
    _run(ref, ref_groups, 20)
    dst_groups = [{**g, "params": [g["params"][0].detach().clone().requires_grad_()]} for g in src_groups]
    dst = Adam(dst_groups, eps=1e-15) if direction == "torch_to_ours" else torch.optim.Adam(dst_groups, lr=0.0,
                                                                                            eps=1e-15)
    dst.load_state_dict(src.state_dict())
    _run(dst, dst_groups, 20, start=20)
    _run(ref, ref_groups, 20, start=20)
    for x, y in zip(dst_groups, ref_groups):
        torch.testing.assert_close(x["params"][0], y["params"][0], rtol=0, atol=1e-6)


def test_bad_arguments():
    with pytest.raises(ValueError, match="betas"):
        Adam(_groups(), betas=(1.0, 0.9))
    with pytest.raises(TypeError, match="floating-point"):
        Adam([{"params": [torch.zeros(3, dtype=torch.long)], "lr": 1.0, "name": "i"}])
    a = Adam(_groups())
    sd = a.state_dict()
    sd["param_groups"] = sd["param_groups"][:1]
    with pytest.raises(ValueError, match="do not match|does not match"):
        a.load_state_dict(sd)
