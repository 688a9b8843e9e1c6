# SPDX-License-Identifier: Apache-2.0
"""What a checkpoint stores of a :class:`~.loop.FitRun` and how it comes back (:meth:`FitRun.checkpoint_state`,
:meth:`FitRun.restore_checkpoint`). The keys stay stable so that checkpoints of earlier runs resume; a key added
later is optional when read."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from .checkpoint import rng_state, set_rng_state
from .proxy import ProxyMesh, region_clip
from .surfels import Surfels

__all__ = ["run_state", "restore_run_state"]


def run_state(run) -> dict:
    """The stored dictionary of ``run``: the last good surfels and optimiser, loop state, RNGs and config (the
    final mesh is made last, after every checkpoint; a checkpoint of an earlier version, whose polish followed the
    mesh, may hold a ``final_mesh``, which is not read: the mesh is made again after the polish)."""
    good = run.last_good
    return {
        "surfels": good[0] if good is not None else run.surfels.state_dict(),
        "optimizer": good[1] if good is not None else run.opt.state_dict(),
        "iteration": run.it, "tsdf_done": run.tsdf_done, "history": run.history, "events": run.events,
        "gap": run.strategy.gap, "loss_sums": dict(run.loss_log.sums), "loss_count": run.loss_log.count,
        "elapsed": run.elapsed(), "timers": dict(run.timers.total), "rng": rng_state(),
        "generator": run.gen.get_state(), "config_hash": run.hash, "config": run.cfg.to_dict(),
        "normalization": {"scale": run.sim.scale, "translation": list(run.sim.translation)},
        "proxy": {"box": None if run.proxy.box is None else [np.asarray(b).tolist() for b in run.proxy.box],
                  "prior": run.proxy.prior},
        "tsdf_info": run.tsdf_info, "coevolution_info": run.coevolution_info,
        "total_failures": run.total_failures,
    }


def restore_run_state(run, st: dict) -> None:
    """Load a stored dictionary (:func:`run_state`) into ``run``."""
    run.set_surfels(Surfels.from_state_dict(st["surfels"], run.device), st["optimizer"])
    run.it = int(st["iteration"])
    run.tsdf_done = bool(st["tsdf_done"])
    run.history = list(st["history"])
    run.events = list(st["events"])
    run.strategy.gap = float(st["gap"])
    run.loss_log.sums = defaultdict(float, st["loss_sums"])
    run.loss_log.count = int(st["loss_count"])
    run.elapsed_before = float(st["elapsed"])
    run.timers.total = defaultdict(float, st["timers"])
    run.total_failures = int(st["total_failures"])
    run.tsdf_info = dict(st["tsdf_info"])
    run.coevolution_info = dict(st.get("coevolution_info", {}))  # absent before the thin-part rule
    set_rng_state(st["rng"])
    run.gen.set_state(st["generator"])
    px = st["proxy"]
    box = None if px["box"] is None else tuple(np.asarray(b) for b in px["box"])
    clip = region_clip(run.cfg.mesh, run.plan.layout)
    run.proxy = ProxyMesh(run.cfg.mesh, box=box, prior=px["prior"], clip=clip)
