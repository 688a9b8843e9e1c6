# SPDX-License-Identifier: Apache-2.0
"""Checkpoints of a running fit: when they are written, and resuming or branching from them.

The files themselves (atomic writes, validation, fallback to the previous checkpoint) are
:mod:`wtopo.fitting.checkpoint`. :class:`Checkpointer` decides the cadence and talks to the fit through
:class:`CheckpointedRun`, a few members the fit loop (:class:`~wtopo.fitting.loop.FitRun`) provides: the
stored dictionary itself (:meth:`CheckpointedRun.checkpoint_state`, whose keys stay stable so checkpoints
of earlier runs resume) is the loop's to write and to load back.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Protocol

from .checkpoint import CheckpointError, list_checkpoints, load_checkpoint, save_checkpoint
from .config import FitConfig
from .profiling import Timers

__all__ = ["Checkpointer", "CheckpointedRun", "AFTER_WARMUP", "DECAY_HORIZON", "RUNTIME_COMPARED", "warmup_differences"]

KEEP_CHECKPOINTS = 2  # checkpoints kept on disk: the newest, and one to fall back on if it is corrupt
CHECKPOINT_SECONDS = 120.0  # also checkpoint when this much wall-clock time passed since the last one

AFTER_WARMUP = ("coevolution.enabled", "final.", "polish.", "mesh.", "losses.mesh_", "densify.geometry_",
                "optim.means_restart")
"""Configuration fields (dotted paths, or prefixes ending in ``.`` or ``_``) that act only after the warm-up:
two fits that differ only in these share their warm-up, so one may start from the other's
(``runtime.start_from``). Of ``runtime`` only :data:`RUNTIME_COMPARED` is compared. ``coevolution.iterations``
and ``optim.means_decay_iterations`` reach the warm-up only through the means' decay horizon
(:data:`DECAY_HORIZON`), which is compared in their place when both configurations give it."""
RUNTIME_COMPARED = ("runtime.seed", "runtime.image_scale", "runtime.max_surfels")
"""The runtime fields that change a warm-up (the rest set devices, cadences and output)."""
DECAY_HORIZON = ("coevolution.iterations", "optim.means_decay_iterations")
"""The fields that set the iteration at which the means' single decay reaches ``optim.means_final``
(:func:`wtopo.fitting.schedule.means_rate`): ``optim.means_decay_iterations``, or else the warm-up's and the
co-evolution's iterations together. A fit with a longer co-evolution and the decay horizon of a shorter one
shares that one's warm-up."""


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _decay_horizon(f: dict) -> int | None:
    """The means' decay horizon of a flattened configuration; ``None`` while the plan has yet to set it."""
    if f.get("optim.means_decay_iterations") is not None:
        return int(f["optim.means_decay_iterations"])
    warm, coevo = f.get("warmup.iterations"), f.get("coevolution.iterations")
    return None if warm is None or coevo is None else int(warm) + int(coevo)


def warmup_differences(a: dict, b: dict) -> list[str]:
    """The dotted fields two configurations (``FitConfig.to_dict()``) differ in that the warm-up reads
    (everything but :data:`AFTER_WARMUP` and the runtime fields other than :data:`RUNTIME_COMPARED`), sorted.

    The fields of :data:`DECAY_HORIZON` that differ are named only when the means' decay horizon differs, or
    when either configuration leaves it to the plan (``coevolution.iterations`` unset)."""
    fa, fb = _flat(a), _flat(b)
    keep = [k for k in set(fa) | set(fb)
            if (k in RUNTIME_COMPARED or not k.startswith("runtime."))
            and not any(k == p or (p[-1] in "._" and k.startswith(p)) for p in AFTER_WARMUP)
            and k not in DECAY_HORIZON]
    out = {k for k in keep if fa.get(k, "<absent>") != fb.get(k, "<absent>")}
    ha, hb = _decay_horizon(fa), _decay_horizon(fb)
    named = [k for k in DECAY_HORIZON if fa.get(k, "<absent>") != fb.get(k, "<absent>")]
    if ha is None or hb is None or ha != hb:
        out.update(named)
    return sorted(out)


class CheckpointedRun(Protocol):
    """What :class:`Checkpointer` needs of the fit it checkpoints."""

    cfg: FitConfig
    """The resolved configuration (its ``runtime`` cadences and ``start_from``)."""
    it: int
    """Iterations done."""
    hash: str
    """The configuration's hash, which a resumed checkpoint must carry."""
    timers: Timers
    """The fit's section timers (writing is timed as ``checkpoint``)."""

    @property
    def warmup_end(self) -> int:
        """Iteration at which the warm-up ends: a branch starts from a checkpoint at or before it."""

    def snapshot(self) -> None:
        """Keep the current state as the last good one."""

    def record(self, event: str, **fields) -> None:
        """Append an event at the current iteration."""

    def checkpoint_state(self) -> dict:
        """The stored dictionary of the last good state (its keys: see :meth:`FitRun.checkpoint_state`)."""

    def restore_checkpoint(self, state: dict) -> None:
        """Load a stored dictionary into the fit."""


class Checkpointer:
    """Writes checkpoints of ``run`` on an iteration and a wall-clock cadence and resumes from them.

    Args:
        run: the fit it belongs to (:class:`~wtopo.fitting.loop.FitRun`).
        out_dir: run directory (checkpoints go to ``out_dir/checkpoints``), or ``None`` for none.
    """

    def __init__(self, run: CheckpointedRun, out_dir: Path | None):
        self.run = run
        self.out_dir = out_dir
        self.directory = None if out_dir is None else out_dir / "checkpoints"
        self._last_time = time.perf_counter()
        self.saved_iteration: int | None = None  # the iteration of the checkpoint last written or resumed here

    def save(self, *, force: bool = False) -> Path | None:
        """Write a checkpoint now; ``force``: of the last good state as it is (a scheduled one first
        snapshots the current, finite state). ``None`` without a run directory."""
        if self.directory is None:
            return None
        r = self.run
        if not force:
            r.snapshot()
        with r.timers("checkpoint"):
            path = save_checkpoint(self.directory, r.it, r.checkpoint_state(), keep=KEEP_CHECKPOINTS)
        self._last_time = time.perf_counter()
        self.saved_iteration = r.it
        return path

    def save_once(self) -> Path | None:
        """:meth:`save`, unless this iteration's checkpoint is already written (by the cadence, or the one this run
        resumed from): the state has not moved since. ``None`` when nothing was written."""
        return None if self.saved_iteration == self.run.it else self.save()

    def maybe_save(self) -> None:
        """Checkpoint when ``runtime.checkpoint_every`` iterations or :data:`CHECKPOINT_SECONDS` have passed."""
        rt, it = self.run.cfg.runtime, self.run.it
        due = ((rt.checkpoint_every and it % rt.checkpoint_every == 0)
               or time.perf_counter() - self._last_time > CHECKPOINT_SECONDS)
        if due:
            self.save()

    def resume(self) -> bool:
        """Load the newest valid checkpoint of this configuration into the run, or, when the run directory
        holds none, branch from ``runtime.start_from`` (:meth:`_branch`); ``False`` when neither applies.

        Raises:
            ValueError: the run directory holds checkpoints this configuration cannot resume, or the branch's
                source cannot be started from.
        """
        d = self.directory
        if d is None or not list_checkpoints(d):
            return self._branch() if self.run.cfg.runtime.start_from else False
        r = self.run
        try:
            st = load_checkpoint(d, config_hash=r.hash)
        except CheckpointError as e:
            raise ValueError(f"{self.out_dir} holds checkpoints this configuration cannot resume ({e}); "
                             "use another out_dir or the configuration of that run") from None
        r.restore_checkpoint(st)
        self.saved_iteration = r.it
        r.record("resumed", **{"from": st["path"]})
        return True

    def _branch(self) -> bool:
        """Start from the newest checkpoint of the run ``runtime.start_from`` names (see its docstring).

        Raises:
            ValueError: no usable checkpoint there, one past the warm-up, or a configuration whose warm-up
                differs from this fit's (the fields are named).
        """
        r = self.run
        src = Path(r.cfg.runtime.start_from)
        folder = src / "checkpoints" if (src / "checkpoints").is_dir() else src
        try:
            st = load_checkpoint(folder)
        except CheckpointError as e:
            raise ValueError(f"runtime.start_from = {str(src)!r}: {e}") from None
        if int(st["iteration"]) > r.warmup_end or st["tsdf_done"]:
            raise ValueError(f"runtime.start_from = {str(src)!r}: its checkpoint is at iteration {st['iteration']}"
                             f"{' after the TSDF re-initialisation' if st['tsdf_done'] else ''}; a branch starts "
                             f"within the warm-up (iterations 0-{r.warmup_end}): make it with runtime.stop_at = "
                             f"{r.warmup_end}")
        diff = warmup_differences(st["config"], r.cfg.to_dict())
        if diff:
            horizon = _decay_horizon(_flat(st["config"]))
            hint = (f"; its co-evolution's length may change with optim.means_decay_iterations = {horizon}, that "
                    f"run's means' decay horizon" if horizon is not None and set(diff) <= set(DECAY_HORIZON) else "")
            raise ValueError(f"runtime.start_from = {str(src)!r}: that run's warm-up differs from this one's in "
                             f"{', '.join(diff)} (a branch may change only what acts after the warm-up{hint})")
        r.restore_checkpoint(st)
        r.record("started_from", **{"from": st["path"], "config_hash": st["config_hash"]})
        return True
