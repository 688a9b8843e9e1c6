# SPDX-License-Identifier: Apache-2.0
"""The pieces :class:`wtopo.io.TimelineWriter` writes with: per-surfel event flags, what a flush wrote, and
one time-sampled attribute that skips repeats (see :mod:`wtopo.io.usd` for the file layout)."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["SurfelEvent", "TimelineStats"]


class SurfelEvent(enum.IntFlag):
    """Per-surfel event flags stored in ``primvars:events`` (bitwise OR)."""

    SPAWNED = 1
    """Created by densification since the previous sample."""
    PRUNED = 2
    """Marked for removal at this sample (still present in it)."""
    FLIPPED = 4
    """Normal sign flipped since the previous sample."""


@dataclass
class TimelineStats:
    """What :meth:`TimelineWriter.flush` wrote.

    Attributes:
        path: the file written.
        samples: number of :meth:`TimelineWriter.add_sample` calls.
        bytes: file size in bytes.
        bytes_per_100_samples: ``100 * bytes / samples`` (``bytes`` when there are no samples).
    """

    path: str
    samples: int
    bytes: int
    bytes_per_100_samples: float


class _Track:
    """One time-sampled attribute: skips repeats, writes hold keys (module docstring)."""

    def __init__(self, attr, make_vt, interpolates: bool):
        self.attr, self.make_vt, self.interpolates = attr, make_vt, interpolates
        self.last = None
        self.last_vt = None
        self.skipped_at = None
        self.count = 0

    def unchanged(self, t: float) -> None:
        if self.last is not None:
            self.skipped_at = t

    def set(self, value: np.ndarray, t: float) -> None:
        if self.last is not None and value.shape == self.last.shape and np.array_equal(value, self.last):
            self.skipped_at = t
            return
        if self.skipped_at is not None and self.interpolates and value.shape == self.last.shape:
            self.attr.Set(self.last_vt, self.skipped_at)
            self.count += 1
        vt = self.make_vt(value)
        self.attr.Set(vt, t)
        self.count += 1
        self.last, self.last_vt, self.skipped_at = value, vt, None
