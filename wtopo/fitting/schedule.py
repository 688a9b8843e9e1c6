"""The means' learning-rate schedule and the shaping of their steps in the co-evolution.

The means decay exponentially from ``optim.means`` to ``optim.means_final`` over the whole fit (or over
``optim.means_decay_iterations``, then stay at ``means_final``; where the thin-part rule fired, a
co-evolution's decay may end sooner, ``optim.means_thin_decay``), or,
with ``optim.means_restart``, restart at the co-evolution where the thin-part rule did not end the decay
sooner (see :class:`~.config.OptimConfig`).
With ``optim.means_restart_along_normal`` the restarted rate moves a surfel only along its normal:
the in-plane part of each step is scaled back to what the single decay would have taken.
"""

from __future__ import annotations

import torch

from .config import OptimConfig


def single_decay(o: OptimConfig, it: int, total: int) -> float:
    """The means rate of one exponential decay over ``total`` iterations, at iteration ``it``."""
    if o.means <= 0 or o.means_final <= 0:
        return o.means
    return o.means * (o.means_final / o.means) ** min(1.0, it / max(1, total))


def means_rate(o: OptimConfig, it: int, warmup_end: int, total: int, thin: bool = False) -> tuple[float, float]:
    """The means' learning rate at iteration ``it`` and the scale of a step's in-plane part.

    Args:
        o: the optimiser configuration.
        it: the iteration (0-based, over both stages).
        warmup_end: the co-evolution's first iteration.
        total: all iterations (warm-up and co-evolution).
        thin: the thin-part rule refined the co-evolution's proxy; with ``optim.means_thin_decay`` the
            co-evolution's rate then follows a single decay ending that fraction of the way through it, and
            ``optim.means_restart`` does not apply.

    Returns:
        ``(rate, in_plane)``: the rate in unit-cube lengths per step, and the factor (in (0, 1]) for
        the part of each step in the surfel's plane: the single decay's rate over ``rate`` when
        ``means_restart_along_normal`` holds in a restarted co-evolution, else 1.
    """
    horizon = total if o.means_decay_iterations is None else int(o.means_decay_iterations)
    thin_end = thin and o.means_thin_decay > 0  # thin parts thin out under a higher rate: no restart either
    if thin_end and it >= warmup_end:
        horizon = min(horizon, warmup_end + max(1, round(o.means_thin_decay * (total - warmup_end))))
    single = single_decay(o, it, horizon)
    restart = o.means_restart or 0.0  # None (left to the plan, unresolved): none
    if restart <= 0 or it < warmup_end or thin_end or o.means <= 0 or o.means_final <= 0:
        return single, 1.0
    start = max(restart * o.means, single_decay(o, warmup_end, horizon))
    frac = min(1.0, (it - warmup_end) / max(1, total - warmup_end))
    rate = start * (o.means_final / start) ** frac
    in_plane = min(1.0, single / rate) if o.means_restart_along_normal else 1.0
    return rate, in_plane


def damp_in_plane_steps(means: torch.Tensor, before: torch.Tensor, normals: torch.Tensor, scale: float) -> None:
    """Scale the in-plane part of the optimiser's last step of ``means`` by ``scale`` (in place).

    Args:
        means: the mean parameter after ``optimizer.step()`` [N, 3].
        before: the means before the step [N, 3] (same N: call before any density change).
        normals: unit normals before the step [N, 3].
        scale: the in-plane factor; the part along the normal is kept.
    """
    with torch.no_grad():
        step = means - before
        along = (step * normals).sum(-1, keepdim=True) * normals
        means.copy_(before + along + scale * (step - along))
