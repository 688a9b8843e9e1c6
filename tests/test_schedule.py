"""The means' rate schedule and the in-plane damping of their steps (wtopo.fitting.schedule)."""

import pytest
import torch

from wtopo.fitting import FitConfig
from wtopo.fitting.schedule import damp_in_plane_steps, means_rate, single_decay


def _optim(restart=0.0, along_normal=False):
    o = FitConfig().optim
    o.means_restart, o.means_restart_along_normal = restart, along_normal
    return o


def test_single_decay_runs_from_means_to_means_final():
    o = _optim()
    assert single_decay(o, 0, 600) == pytest.approx(o.means)
    assert single_decay(o, 300, 600) == pytest.approx((o.means * o.means_final) ** 0.5)
    assert single_decay(o, 600, 600) == pytest.approx(o.means_final)
    assert single_decay(o, 900, 600) == pytest.approx(o.means_final)  # held past the end


@pytest.mark.parametrize("along_normal", [False, True])
def test_means_rate_restarts_and_reports_the_in_plane_scale(along_normal):
    o = _optim(0.3, along_normal)
    # the warm-up is the single decay, in-plane untouched
    assert means_rate(o, 100, 400, 600) == pytest.approx((single_decay(o, 100, 600), 1.0))
    rate, in_plane = means_rate(o, 400, 400, 600)
    assert rate == pytest.approx(0.3 * o.means)
    single = single_decay(o, 400, 600)
    assert in_plane == pytest.approx(single / rate if along_normal else 1.0)
    assert 0 < in_plane <= 1
    rate, in_plane = means_rate(o, 600, 400, 600)
    assert rate == pytest.approx(o.means_final) and in_plane == pytest.approx(1.0)  # both end at means_final


def test_without_a_restart_along_normal_changes_nothing():
    o = _optim(0.0, True)
    for it in (0, 399, 400, 599):
        assert means_rate(o, it, 400, 600) == pytest.approx((single_decay(o, it, 600), 1.0))


def test_damp_in_plane_steps_keeps_the_normal_part():
    torch.manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64), dim=-1)
    before = torch.randn(64, 3, dtype=torch.float64)
    step = torch.randn(64, 3, dtype=torch.float64)
    means = before + step
    damp_in_plane_steps(means, before, n, 0.25)
    got = means - before
    along = (step * n).sum(-1)
    assert torch.allclose((got * n).sum(-1), along)  # the normal part is kept
    in_plane = step - along[:, None] * n
    assert torch.allclose(got - (got * n).sum(-1, keepdim=True) * n, 0.25 * in_plane)
    assert in_plane.norm(dim=-1).min() > 1e-3  # the case exercised an in-plane part


def test_damp_in_plane_steps_analytic():
    before = torch.zeros(2, 3)
    means = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, -1.0]])
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    damp_in_plane_steps(means, before, normals, 0.5)
    assert torch.equal(means, torch.tensor([[0.5, 1.0, 3.0], [0.0, 0.0, -1.0]]))
    damp_in_plane_steps(means, before, normals, 1.0)  # scale 1: unchanged
    assert torch.equal(means, torch.tensor([[0.5, 1.0, 3.0], [0.0, 0.0, -1.0]]))


def test_means_decay_iterations_keeps_a_shorter_schedules_rates():
    """A decay over ``means_decay_iterations`` gives a lengthened fit the shorter schedule's rates, then holds
    ``means_final`` (its bad values: tests/test_fit_config.py)."""
    o = _optim()
    o.means_decay_iterations = 1200
    for it in (0, 400, 800, 1199):  # 800 + 800 with the rates of 800 + 400
        assert means_rate(o, it, 800, 1600) == pytest.approx((single_decay(o, it, 1200), 1.0))
    assert means_rate(o, 800, 800, 1600)[0] < means_rate(_optim(), 800, 800, 1600)[0]  # 7.4e-5 against 1.6e-4
    assert means_rate(o, 1400, 800, 1600) == pytest.approx((o.means_final, 1.0))
    # a restart never starts below the decay in use (1,200 iterations here, not the fit's 1,600)
    o.means_restart = 0.01  # 1.6e-5: under the decay's 7.4e-5 at the co-evolution's start
    assert means_rate(o, 800, 800, 1600)[0] == pytest.approx(single_decay(o, 800, 1200))


def test_means_thin_decay_shortens_only_a_thin_co_evolutions_decay():
    """``means_thin_decay``: where the thin-part rule fired, the co-evolution's rate is a single decay that ends
    that fraction of the way through it (0.5 of 800 + 800: 800 + 400's rates); the warm-up, a fit where the rule
    did not fire and 0 (off) keep the fit's own decay."""
    o, off = _optim(), _optim()
    o.means_thin_decay, off.means_thin_decay = 0.5, 0.0
    for it in (0, 799):  # the warm-up: unchanged
        assert means_rate(o, it, 800, 1600, thin=True) == means_rate(off, it, 800, 1600)
    for it in (800, 1000, 1199):
        assert means_rate(o, it, 800, 1600, thin=True) == pytest.approx((single_decay(o, it, 1200), 1.0))
        assert means_rate(o, it, 800, 1600, thin=False) == means_rate(off, it, 800, 1600)
        assert means_rate(off, it, 800, 1600, thin=True) == means_rate(off, it, 800, 1600)
    assert means_rate(o, 800, 800, 1600, thin=True)[0] < 0.5 * means_rate(o, 800, 800, 1600)[0]
    assert means_rate(o, 1500, 800, 1600, thin=True) == pytest.approx((o.means_final, 1.0))
    o.means_decay_iterations = 1000  # a shorter decay already in use stays
    assert means_rate(o, 1100, 800, 1600, thin=True) == pytest.approx((o.means_final, 1.0))


def test_a_thin_co_evolution_keeps_its_decay_where_the_rest_restart():
    """``means_restart`` raises the co-evolution's rate only where the thin-part rule did not end its decay sooner
    (thin parts thin out under a higher rate): the CUDA budget's horizon of 4,000 in 3,000 + 2,000, restarted at
    1e-4; a thin fit keeps the single decay, and with ``means_thin_decay`` off the restart applies to it too."""
    o = _optim()
    o.means_decay_iterations, o.means_restart = 4000, 0.0625
    assert means_rate(o, 3000, 3000, 5000)[0] == pytest.approx(1e-4)  # 0.0625 x 1.6e-3, over the decay's 5.1e-5
    assert means_rate(o, 4000, 3000, 5000)[0] == pytest.approx((1e-4 * o.means_final) ** 0.5)
    assert means_rate(o, 4999, 3000, 5000)[0] == pytest.approx(o.means_final, rel=1e-3)
    for it in (2999, 3000, 3500, 4000, 4999):
        assert means_rate(o, it, 3000, 5000, thin=True) == pytest.approx((single_decay(o, it, 4000), 1.0))
    o.means_thin_decay = 0.0
    assert means_rate(o, 3500, 3000, 5000, thin=True) == means_rate(o, 3500, 3000, 5000)
