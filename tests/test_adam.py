# SPDX-License-Identifier: Apache-2.0
"""The fit's Adam (:mod:`wtopo.fitting.adam`) against ``torch.optim.Adam``:
the same parameters after many steps with changing rates and gradients that skip a step (float32 and float64, on
every device), non-finite gradients zeroed and flagged, non-finite results flagged, and state dicts that load both
ways."""

from __future__ import annotations

import pytest
import torch

from wtopo.fitting.adam import Adam


def _groups(seed=0, dtype=torch.float32, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    return [{"params": [torch.randn(40, 3, generator=g, dtype=dtype).to(device).requires_grad_()], "lr": 1e-2,
             "name": "a"},
            {"params": [torch.randn(40, generator=g, dtype=dtype).to(device).requires_grad_()], "lr": 5e-2,
             "name": "b"}]


def _run(opt, groups, steps, seed=1, start=0):
    g = torch.Generator().manual_seed(seed)
    for k in range(start, start + steps):
        for grp in groups:
            p = grp["params"][0]
            if k % 7 == 3 and grp["name"] == "b":  # a step without a gradient for one group
                p.grad = None
                continue
            p.grad = (torch.randn(p.shape, generator=g, dtype=p.dtype) * (1 + k % 5)).to(p.device)
        opt.param_groups[0]["lr"] = 1e-2 * 0.97 ** k  # a decaying rate, as the means'
        opt.step()
        opt.zero_grad(set_to_none=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_torch_adam(device, dtype):
    ours, theirs = _groups(dtype=dtype, device=device), _groups(dtype=dtype, device=device)
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


def test_non_finite_gradients_are_zeroed_and_flagged(device):
    """A NaN or infinite gradient element updates as a zero gradient would, and the step's flag says so; a finite
    step's flag is 0; a non-finite result is flagged; no gradient at all: no flag."""
    ours, theirs = _groups(device=device), _groups(device=device)
    a = Adam(ours)
    b = torch.optim.Adam(theirs, lr=0.0)
    for x, y in zip(ours, theirs):
        y["lr"] = x["lr"]
    bad = torch.randn(40, 3, generator=torch.Generator().manual_seed(2)).to(device)
    bad[3, 1], bad[7, 0], bad[9, 2] = float("nan"), float("inf"), -float("inf")
    ours[0]["params"][0].grad, theirs[0]["params"][0].grad = bad.clone(), torch.nan_to_num(bad, 0.0, 0.0, 0.0)
    ours[1]["params"][0].grad = theirs[1]["params"][0].grad = None
    finite = a.step()
    b.step()
    assert not bool(finite)
    assert bool(torch.isfinite(ours[0]["params"][0].grad).all()) and float(ours[0]["params"][0].grad[3, 1]) == 0.0
    torch.testing.assert_close(ours[0]["params"][0], theirs[0]["params"][0], rtol=0, atol=1e-6)
    ours[0]["params"][0].grad = torch.ones(40, 3, device=device)
    assert bool(a.step())
    with torch.no_grad():
        ours[1]["params"][0][5] = float("inf")  # a parameter that is already infinite stays so
    ours[1]["params"][0].grad = torch.ones(40, device=device)
    assert not bool(a.step())
    with torch.no_grad():
        ours[1]["params"][0][5] = 0.0
    ours[1]["params"][0].grad = torch.ones(40, device=device)
    assert bool(a.step())
    ours[0]["params"][0].grad = torch.full((40, 3), 1e25, device=device)  # finite, but its square's moment is not
    assert not bool(a.step())
    a.zero_grad()
    assert a.step() is None


def test_bad_arguments():
    with pytest.raises(ValueError, match="betas"):
        Adam(_groups(), betas=(1.0, 0.9))
    with pytest.raises(TypeError, match="floating-point"):
        Adam([{"params": [torch.zeros(3, dtype=torch.long)], "lr": 1.0, "name": "i"}])
    with pytest.raises(ValueError, match="contiguous"):
        Adam([{"params": [torch.zeros(3, 4).t()], "lr": 1.0, "name": "t"}])
    a = Adam(_groups())
    sd = a.state_dict()
    sd["param_groups"] = sd["param_groups"][:1]
    with pytest.raises(ValueError, match="do not match|does not match"):
        a.load_state_dict(sd)


def _graph_modes(device):
    """(label, setup) pairs for the update's graph path: emulated (its fixed buffers and device rates, run without a
    capture) on every device, captured on CUDA."""
    modes = [("emulated", lambda a: setattr(a, "_emulate", True))]
    if str(device).startswith("cuda"):
        modes.append(("captured", lambda a: None))
    return modes


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_graph_path_matches_the_eager_update(device, dtype, monkeypatch):
    """The graph's update (rates as device tensors, divided as torch's capturable Adam does; gradients copied into
    fixed buffers) follows the eager one over many steps, through a step without one group's gradient (another
    graph), a parameter replaced as a densification step replaces it (a new graph, its first step eager) and a rate
    that changes at every step; each parameter's gradient is the step's cleaned buffer afterwards."""
    import wtopo.fitting.adam as adam_mod

    for label, setup in _graph_modes(device):
        ours, ref = _groups(dtype=dtype, device=device), _groups(dtype=dtype, device=device)
        a, b = Adam(ours, eps=1e-15), Adam(ref, eps=1e-15)
        setup(a)
        monkeypatch.setattr(adam_mod, "GRAPHS", True)
        b._emulate = False
        _run(a, ours, 30)
        monkeypatch.setattr(adam_mod, "GRAPHS", False)  # the reference runs eagerly on CUDA too
        _run(b, ref, 30)
        monkeypatch.setattr(adam_mod, "GRAPHS", True)
        assert a.graph_failure is None, label
        assert len(a._graphs) == 2, label  # with and without group b's gradient
        for opt, groups in ((a, ours), (b, ref)):  # a densification step: a longer parameter and moments
            grp, p = groups[0], groups[0]["params"][0]
            st = opt.state.pop(p)
            new = torch.cat([p.detach(), p.detach()[:5]]).requires_grad_()
            opt.state[new] = {"step": st["step"], **{k: torch.cat([st[k], st[k][:5]]) for k in ("exp_avg",
                                                                                                "exp_avg_sq")}}
            grp["params"][0] = opt.param_groups[0]["params"][0] = new
        _run(a, ours, 30, start=30)
        monkeypatch.setattr(adam_mod, "GRAPHS", False)
        _run(b, ref, 30, start=30)
        monkeypatch.setattr(adam_mod, "GRAPHS", True)
        tol = 1e-6 if dtype == torch.float32 else 1e-12
        for x, y in zip(ours, ref):
            torch.testing.assert_close(x["params"][0], y["params"][0], rtol=0, atol=tol, msg=label)
            torch.testing.assert_close(a.state[x["params"][0]]["exp_avg"], b.state[y["params"][0]]["exp_avg"],
                                       rtol=0, atol=tol, msg=label)
        p = ours[0]["params"][0]
        bad = torch.ones_like(p)
        bad[2, 1] = float("nan")
        p.grad = bad
        finite = a.step()
        assert not bool(finite), label
        assert p.grad is not bad and float(p.grad[2, 1]) == 0.0 and bool(torch.isfinite(p.grad).all()), label
        p.grad = torch.ones_like(p)
        ours[1]["params"][0].grad = torch.ones_like(ours[1]["params"][0])
        assert bool(a.step()), label


def test_a_graph_that_disagrees_with_the_eager_update_is_dropped(device, monkeypatch):
    """A graph whose first replay differs from the eager update of the same state (here an emulated graph with a
    wrong second-moment rate) is not used again: the step keeps the eager result, warns and says why, and the
    steps after it run eagerly, to the parameters of the eager optimiser."""
    import wtopo.fitting.adam as adam_mod

    def wrong_body(self):
        for bucket in self.buckets:
            bucket[-1][1].mul_(2.0)  # every root correction doubled
        return good_body(self)

    good_body = adam_mod._StepGraph._body
    monkeypatch.setattr(adam_mod._StepGraph, "_body", wrong_body)
    ours, ref = _groups(device=device), _groups(device=device)
    for groups in (ours, ref):  # an empty parameter, as the SH bands above degree 0 of a diffuse fit ([N, 0, 3])
        groups.append({"params": [torch.zeros(40, 0, 3, device=device, requires_grad=True)], "lr": 1e-3,
                       "name": "empty"})
    a, b = Adam(ours, eps=1e-15), Adam(ref, eps=1e-15)
    a._emulate = True
    with pytest.warns(RuntimeWarning, match="differs from the eager update") as caught:
        _run(a, ours, 12)
    assert len(caught) == 1
    monkeypatch.setattr(adam_mod, "GRAPHS", False)
    _run(b, ref, 12)
    assert "differs" in a.graph_failure and not a._graphs
    for x, y in zip(ours, ref):
        torch.testing.assert_close(x["params"][0], y["params"][0], rtol=0, atol=1e-6)
