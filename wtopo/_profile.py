# SPDX-License-Identifier: Apache-2.0
"""Named wall-clock sections with self time: the project's one profiler.

Collected by the per-stage times of :func:`wtopo.fit` and by benchmark scripts (the rasterizer's
``rasterize_binning``, ``rasterize_sort``, ``rasterize_forward`` and ``rasterize_backward`` sections).

``section(name)`` costs one context-variable lookup when nothing collects. Inside a collecting
section (one opened with ``add=``, as the fit's timers do), every nested section reports its
*self* time (its wall time minus that of the sections nested in it) to the collector, so the
times of all sections add up to the wall time of the outermost one and nothing is counted twice:
the fit's ``"raycast"`` excludes the ``"bvh_build"`` inside it, ``"poisson"`` excludes the
``"scatter"`` inside it, ``"render"`` the rasterizer's sections inside it.

A collector may also take ``record(path, self_seconds, seconds)``, called at every section's end
with the names of the open sections from the outermost (a call tree: ``("tsdf", "tsdf_fusion",
"marching_cubes")`` is not the proxy's ``("proxy", "marching_cubes")``), and ``sync()``, called
at every section's start and end (but the start of one opened with ``synced``, whose caller
synchronised): the fit's ``runtime.profile`` passes ``torch.cuda.synchronize`` so that on CUDA
each section is charged its own kernels. Without ``sync`` no section synchronises.

Limitations:
    Wall-clock host time: without ``sync``, kernels still running when a section ends on CUDA are
    charged to the section that next synchronises. Sections opened in other threads (CUDA
    autograd's backward thread among them) are not collected: they count in the section around.
"""

from __future__ import annotations

import contextvars
import time
from collections.abc import Callable
from contextlib import AbstractContextManager

__all__ = ["section", "in_section"]


class _Collector:
    def __init__(self, add: Callable[[str, float], None], sync: Callable[[], None] | None,
                 record: Callable[[tuple[str, ...], float, float], None] | None):
        self.add = add
        self.sync = sync
        self.record = record
        self.child_time: list[float] = []  # per open section: wall time of its nested sections
        self.names: list[str] = []  # the open sections, outermost first


_ACTIVE: contextvars.ContextVar[_Collector | None] = contextvars.ContextVar("wtopo_profile", default=None)


def in_section() -> bool:
    """Whether a collecting section is open in this context."""
    return _ACTIVE.get() is not None


class _Section:
    """One timed block (what :func:`section` returns): a plain context manager, a few microseconds a use."""

    __slots__ = ("name", "add", "sync", "record", "synced", "col", "token", "t")

    def __init__(self, name, add, sync, record, synced):
        self.name, self.add, self.sync, self.record, self.synced = name, add, sync, record, synced

    def __enter__(self) -> None:
        col = _ACTIVE.get()
        self.token = None
        if col is None:
            if self.add is None:
                self.col = None
                return
            col = _Collector(self.add, self.sync, self.record)
            self.token = _ACTIVE.set(col)
        self.col = col
        if col.sync is not None and not (self.synced and self.token is not None):
            col.sync()
        col.child_time.append(0.0)
        col.names.append(self.name)
        self.t = time.perf_counter()

    def __exit__(self, *exc) -> bool:
        col = self.col
        if col is None:
            return False
        try:
            if col.sync is not None:
                col.sync()
        finally:
            dt = time.perf_counter() - self.t
            nested = col.child_time.pop()
            col.add(self.name, dt - nested)
            if col.record is not None:
                col.record(tuple(col.names), dt - nested, dt)
            col.names.pop()
            if col.child_time:
                col.child_time[-1] += dt
            if self.token is not None:
                _ACTIVE.reset(self.token)
        return False


def section(name: str, add: Callable[[str, float], None] | None = None, *, sync: Callable[[], None] | None = None,
            record: Callable[[tuple[str, ...], float, float], None] | None = None,
            synced: bool = False) -> AbstractContextManager[None]:
    """A context manager timing the enclosed block as ``name`` (self time, seconds) when a collector is active.

    Args:
        name: section name.
        add: ``add(name, seconds)``; when no collector is active this section becomes one and
            receives its own self time and that of every section nested in it. Ignored inside
            an active collector (the outer one receives everything), as are ``sync`` and ``record``.
        sync: with ``add``, called at the start and end of this section and of every one nested in it
            (a device synchronisation).
        record: with ``add``, ``record(path, self_seconds, seconds)`` at the end of this section and of
            every one nested in it; ``path`` names the open sections from the outermost to this one.
        synced: with ``add``, the caller synchronised just before: this section skips its start ``sync``.
    """
    return _Section(name, add, sync, record, synced)
