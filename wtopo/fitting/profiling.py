# SPDX-License-Identifier: Apache-2.0
"""Where a fit spends its time: the fit's section timers and the ``runtime.profile`` table.

:class:`Timers` opens the fit's top-level sections (``wtopo._profile.section``): ``render``,
``losses``, ``backward``, ``optimizer``, ``statistics``, ``release`` (the step's gradients and buffers freed),
``densify``, ``guidance``, ``proxy``, ``raycast``,
``tsdf``, ``final``, ``evaluate``, ``checkpoint``, ``timeline``, ``outputs`` (the report and the run
directory's files). The ops open theirs inside
(``rasterize_*``, ``oriented_points``, ``poisson`` / ``scatter``, ``marching_cubes``,
``bvh_build``, ``render_depths``, ``tsdf_fusion`` / ``tsdf_blocks`` / ``tsdf_integrate``). It
always keeps the self time per name (``report["stage_times_s"]``, history records, checkpoints)
and, per call path, the time, self time and calls that :meth:`Timers.profile` turns into the
profile: one row per path with total seconds, calls, milliseconds per call and the share of
the wall time; :func:`format_profile` prints it.

With ``sync`` (``runtime.profile`` on CUDA: ``torch.cuda.synchronize``) every section waits for
the device at its start and end, so each is charged its own kernels; without it no section
synchronises (the fit's default: no host synchronisation is added). The wait at a top-level section's start
(the device finishing what was queued outside any section, and the synchronisation's own cost, which an
unprofiled fit does not pay) is its own row, so "outside any section" is host time.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import AbstractContextManager

from .._profile import in_section, section

__all__ = ["Timers", "format_profile"]

LABELS = {
    "render": "render forward",
    "setup": "setup (plan, scene on the device)",
    "init": "initial surfels (stereo, shells)",
    "stereo_sweep": "plane sweep",
    "stereo_confirm": "stereo confirmation",
    "init_seed": "surfels from the points",
    "init_shells": "background shells",
    "init_setup": "optimiser set-up",
    "rasterize_binning": "binning",
    "rasterize_sort": "depth sort",
    "rasterize_forward": "rasterize",
    "rasterize_backward": "rasterizer backward",
    "losses": "losses",
    "backward": "backward",
    "optimizer": "optimizer",
    "read": "host read (losses, flags)",
    "statistics": "density statistics",
    "release": "freeing the step's buffers",
    "snapshot": "last good state (copy)",
    "densify": "density control",
    "guidance": "mesh guidance",
    "proxy": "proxy mesh",
    "oriented_points": "oriented points",
    "poisson": "Poisson",
    "scatter": "scatter",
    "marching_cubes": "marching cubes",
    "raycast": "proxy ray cast",
    "bvh_build": "BVH build",
    "tsdf": "TSDF re-initialisation",
    "final": "final mesh",
    "render_depths": "render depths",
    "tsdf_fusion": "TSDF fusion",
    "tsdf_upload": "upload views",
    "tsdf_blocks": "block test",
    "tsdf_integrate": "integrate",
    "evaluate": "evaluation",
    "checkpoint": "checkpoint",
    "timeline": "USD timeline",
    "timeline_copy": "the samples' host copies",
    "timeline_send": "their hand-over to the writer",
    "timeline_wait": "the wait for its writer at the end",
    "outputs": "report and output files",
}
"""What the table calls each section (sections without an entry show their name)."""

ORDER = ("setup", "init", "render", "losses", "read", "backward", "optimizer", "statistics", "snapshot", "release",
         "densify", "guidance", "proxy", "raycast", "tsdf", "final", "evaluate", "checkpoint", "timeline", "outputs")
"""Order of the top-level rows (the loop's order); nested rows follow by time."""


class Timers:
    """The fit's section timers: ``timers(name)`` is a context manager timing one top-level section.

    Args:
        sync: called at the start and end of every section (a device synchronisation), or ``None``.

    Attributes:
        total: self seconds per section name, over every path (stored in checkpoints).
        paths: per call path (names from the outermost), ``[seconds, self seconds, calls]``; this
            process only (a resumed fit starts it anew).
    """

    def __init__(self, sync: Callable[[], None] | None = None):
        self.sync = sync
        self.sync_s = 0.0  # the waits of the top-level sections' start synchronisations (profiling's own cost)
        self.total: dict[str, float] = defaultdict(float)
        self.paths: dict[tuple[str, ...], list] = {}

    def _add(self, name: str, seconds: float) -> None:
        self.total[name] += seconds

    def _record(self, path: tuple[str, ...], self_seconds: float, seconds: float) -> None:
        row = self.paths.setdefault(path, [0.0, 0.0, 0])
        row[0] += seconds
        row[1] += self_seconds
        row[2] += 1

    def __call__(self, name: str) -> AbstractContextManager[None]:
        """A context manager timing the block as section ``name`` (nested sections are subtracted). With ``sync``,
        a top-level section's start synchronisation is timed apart (:attr:`sync_s`): it waits for what was queued
        before the section, and only a profiled fit pays it. Use it at once in a ``with`` statement (the
        synchronisation happens at this call)."""
        synced = self.sync is not None and not in_section()
        if synced:
            t = time.perf_counter()
            self.sync()
            self.sync_s += time.perf_counter() - t
        return section(name, add=self._add, sync=self.sync, record=self._record, synced=synced)

    def profile(self, wall: float) -> dict:
        """The profile of this process's sections against ``wall`` seconds, JSON-ready.

        Returns:
            ``{"wall_s", "synchronized", "sections_s", "sync_s", "outside_s", "rows"}``: ``sections_s``
            sums the top-level sections (nested ones are inside them), ``sync_s`` the top-level sections'
            start synchronisations (:attr:`sync_s`: the profile's own cost), ``outside_s`` is the rest of the
            wall time; ``rows`` in table order, each ``{"path", "label", "depth", "total_s", "self_s",
            "calls", "ms_per_call", "percent_wall"}`` (``path`` joins the names with ``/``).
        """
        children: dict[tuple[str, ...], list[tuple[str, ...]]] = defaultdict(list)
        for p in self.paths:
            children[p[:-1]].append(p)
        rank = {n: i for i, n in enumerate(ORDER)}
        rows: list[dict] = []

        def visit(path: tuple[str, ...]) -> None:
            seconds, own, calls = self.paths[path]
            rows.append({"path": "/".join(path), "label": LABELS.get(path[-1], path[-1]), "depth": len(path) - 1,
                         "total_s": round(seconds, 4), "self_s": round(own, 4), "calls": calls,
                         "ms_per_call": round(1000 * seconds / max(calls, 1), 3),
                         "percent_wall": round(100 * seconds / wall, 2) if wall > 0 else 0.0})
            for c in sorted(children[path], key=lambda c: -self.paths[c][0]):
                visit(c)

        for top in sorted(children[()], key=lambda p: (rank.get(p[0], len(ORDER)), -self.paths[p][0])):
            visit(top)
        inside = sum(self.paths[p][0] for p in children[()])
        return {"wall_s": round(wall, 3), "synchronized": self.sync is not None, "sections_s": round(inside, 3),
                "sync_s": round(self.sync_s, 3), "outside_s": round(wall - inside - self.sync_s, 3), "rows": rows}


def format_profile(profile: dict) -> str:
    """The profile of :meth:`Timers.profile` as a text table (one line per section, nested ones indented)."""
    sync = ("each section synchronised with the device" if profile["synchronized"]
            else "host wall time, sections not synchronised")
    lines = [f"wtopo fit profile: {profile['wall_s']:.2f} s wall ({sync})",
             f"  {'stage':<34} {'total s':>9} {'self s':>9} {'calls':>7} {'ms/call':>9} {'% wall':>7}"]
    for r in profile["rows"]:
        label = "  " * r["depth"] + r["label"]
        lines.append(f"  {label:<34} {r['total_s']:9.3f} {r['self_s']:9.3f} {r['calls']:7d} {r['ms_per_call']:9.2f} "
                     f"{r['percent_wall']:7.1f}")
    wall = profile["wall_s"]
    totals = [("all sections", profile["sections_s"])]
    if profile.get("synchronized"):
        totals.append(("waits before sections (profile)", profile.get("sync_s", 0.0)))
    totals.append(("outside any section", profile["outside_s"]))
    for label, s in totals:
        lines.append(f"  {label:<34} {s:9.3f} {'':>9} {'':>7} {'':>9} {100 * s / wall if wall > 0 else 0.0:7.1f}")
    return "\n".join(lines)
