# SPDX-License-Identifier: Apache-2.0
"""The means' learning-rate schedule.

The means decay exponentially from ``optim.means`` to ``optim.means_final`` over the whole fit (or over
``optim.means_decay_iterations``, then stay at ``means_final``; where the thin-part rule fired, the
co-evolution's decay ends :data:`THIN_DECAY` of the way through it), or, with ``optim.means_restart``,
restart at the co-evolution where the thin-part rule did not fire (see :class:`~.config.OptimConfig`).
"""

from __future__ import annotations

from .config import OptimConfig

__all__ = ["THIN_DECAY", "single_decay", "means_rate"]

THIN_DECAY = 0.5
"""Where the thin-part rule refined the proxy's grid, the co-evolution's means reach ``optim.means_final`` this
fraction of the way through the co-evolution (thin parts thin out under a higher rate); 0 would keep the fit's
own decay."""


def single_decay(o: OptimConfig, it: int, total: int) -> float:
    """The means rate of one exponential decay over ``total`` iterations, at iteration ``it``."""
    if o.means <= 0 or o.means_final <= 0:
        return o.means
    return o.means * (o.means_final / o.means) ** min(1.0, it / max(1, total))


def means_rate(o: OptimConfig, it: int, warmup_end: int, total: int, thin: bool = False,
               thin_decay: float = THIN_DECAY) -> float:
    """The means' learning rate at iteration ``it`` [unit-cube lengths per step].

    Args:
        o: the optimiser configuration.
        it: the iteration (0-based, over both stages).
        warmup_end: the co-evolution's first iteration.
        total: all iterations (warm-up and co-evolution).
        thin: the thin-part rule refined the co-evolution's proxy; the co-evolution's rate then follows a
            single decay ending ``thin_decay`` of the way through it, and ``optim.means_restart`` does not apply.
        thin_decay: that fraction (0: the fit's own decay, and the restart applies).
    """
    horizon = total if o.means_decay_iterations is None else int(o.means_decay_iterations)
    thin_end = thin and thin_decay > 0  # thin parts thin out under a higher rate: no restart either
    if thin_end and it >= warmup_end:
        horizon = min(horizon, warmup_end + max(1, round(thin_decay * (total - warmup_end))))
    single = single_decay(o, it, horizon)
    restart = o.means_restart or 0.0  # None (left to the plan, unresolved): none
    if restart <= 0 or it < warmup_end or thin_end or o.means <= 0 or o.means_final <= 0:
        return single
    start = max(restart * o.means, single_decay(o, warmup_end, horizon))
    frac = min(1.0, (it - warmup_end) / max(1, total - warmup_end))
    return start * (o.means_final / start) ** frac
