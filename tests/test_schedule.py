"""The means' rate schedule (wtopo.fitting.schedule)."""

import pytest

from wtopo.fitting import FitConfig
from wtopo.fitting.schedule import THIN_DECAY, means_rate, single_decay


def _optim(restart=0.0):
    o = FitConfig().optim
    o.means_restart = restart
    return o


def test_single_decay_runs_from_means_to_means_final():
    """Decay exponentially from ``means`` to ``means_final`` and hold it past the end."""
    o = _optim()
    assert single_decay(o, 0, 600) == pytest.approx(o.means)
    assert single_decay(o, 300, 600) == pytest.approx((o.means * o.means_final) ** 0.5)
    assert single_decay(o, 600, 600) == pytest.approx(o.means_final)
    assert single_decay(o, 900, 600) == pytest.approx(o.means_final)  # held past the end


def test_means_rate_restarts_at_the_coevolution():
    """Keep the single decay in the warm-up; restart at ``means_restart * means`` and end at ``means_final``."""
    o = _optim(0.3)
    assert means_rate(o, 100, 400, 600) == pytest.approx(single_decay(o, 100, 600))
    assert means_rate(o, 400, 400, 600) == pytest.approx(0.3 * o.means)
    assert means_rate(o, 600, 400, 600) == pytest.approx(o.means_final)


def test_without_a_restart_the_rate_is_the_single_decay():
    """Follow the single decay over both stages when ``means_restart`` is 0."""
    o = _optim(0.0)
    for it in (0, 399, 400, 599):
        assert means_rate(o, it, 400, 600) == pytest.approx(single_decay(o, it, 600))


def test_means_decay_iterations_keeps_a_shorter_schedules_rates():
    """A decay over ``means_decay_iterations`` gives a lengthened fit the shorter schedule's rates, then holds
    ``means_final`` (its bad values: tests/test_fit_config.py)."""
    o = _optim()
    o.means_decay_iterations = 1200
    for it in (0, 400, 800, 1199):  # 800 + 800 with the rates of 800 + 400
        assert means_rate(o, it, 800, 1600) == pytest.approx(single_decay(o, it, 1200))
    assert means_rate(o, 800, 800, 1600) < means_rate(_optim(), 800, 800, 1600)  # 7.4e-5 against 1.6e-4
    assert means_rate(o, 1400, 800, 1600) == pytest.approx(o.means_final)
    # a restart never starts below the decay in use (1,200 iterations here, not the fit's 1,600)
    o.means_restart = 0.01  # 1.6e-5: under the decay's 7.4e-5 at the co-evolution's start
    assert means_rate(o, 800, 800, 1600) == pytest.approx(single_decay(o, 800, 1200))


def test_the_thin_decay_shortens_only_a_thin_co_evolutions_decay():
    """Where the thin-part rule fired, the co-evolution's rate is a single decay that ends ``THIN_DECAY`` of the
    way through it (0.5 of 800 + 800: 800 + 400's rates); the warm-up, a fit where the rule did not fire and a
    thin decay of 0 (off) keep the fit's own decay."""
    assert THIN_DECAY == 0.5
    o = _optim()
    for it in (0, 799):  # the warm-up: unchanged
        assert means_rate(o, it, 800, 1600, thin=True) == means_rate(o, it, 800, 1600)
    for it in (800, 1000, 1199):
        assert means_rate(o, it, 800, 1600, thin=True) == pytest.approx(single_decay(o, it, 1200))
        assert means_rate(o, it, 800, 1600, thin=True, thin_decay=0.0) == means_rate(o, it, 800, 1600)
    assert means_rate(o, 800, 800, 1600, thin=True) < 0.5 * means_rate(o, 800, 800, 1600)
    assert means_rate(o, 1500, 800, 1600, thin=True) == pytest.approx(o.means_final)
    o.means_decay_iterations = 1000  # a shorter decay already in use stays
    assert means_rate(o, 1100, 800, 1600, thin=True) == pytest.approx(o.means_final)


def test_a_thin_co_evolution_keeps_its_decay_where_the_rest_restart():
    """``means_restart`` raises the co-evolution's rate only where the thin-part rule did not end its decay sooner
    (thin parts thin out under a higher rate): the CUDA budget's horizon of 4,000 in 3,000 + 2,000, restarted at
    1e-4; a thin fit keeps the single decay, and with a thin decay of 0 the restart applies to it too."""
    o = _optim()
    o.means_decay_iterations, o.means_restart = 4000, 0.0625
    assert means_rate(o, 3000, 3000, 5000) == pytest.approx(1e-4)  # 0.0625 x 1.6e-3, over the decay's 5.1e-5
    assert means_rate(o, 4000, 3000, 5000) == pytest.approx((1e-4 * o.means_final) ** 0.5)
    assert means_rate(o, 4999, 3000, 5000) == pytest.approx(o.means_final, rel=1e-3)
    for it in (2999, 3000, 3500, 4000, 4999):
        assert means_rate(o, it, 3000, 5000, thin=True) == pytest.approx(single_decay(o, it, 4000))
    assert means_rate(o, 3500, 3000, 5000, thin=True, thin_decay=0.0) == means_rate(o, 3500, 3000, 5000)
