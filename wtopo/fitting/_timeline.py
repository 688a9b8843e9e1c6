# SPDX-License-Identifier: Apache-2.0
"""The USD timeline of a fit: training cameras, surfels and proxy mesh every ``runtime.usd_every``
iterations, and the final mesh, all in the caller's frame (``out_dir/timeline.usdc``).

The fit copies each sample to the host, in the caller's frame, and hands it to a writer in a child process
(:class:`wtopo.io._timeline_process.TimelineProcess`), which authors it on a core of its own while the fit goes
on: a loop bound by its host's Python does not share the GIL with the authoring. The timeline is optional output:
when its writer fails (it cannot start, dies, or raises), the fit warns once, records why
(:attr:`FitTimeline.failure`) and goes on without it; no ``timeline.usdc`` is written.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
import trimesh

from .._profile import section
from .proxy import ProxyResult
from .surfels import Surfels

__all__ = ["FitTimeline", "aborted_on_failure"]


def _host(t: torch.Tensor) -> np.ndarray:
    """``t`` on the host (on the CPU the parameter's own memory: the writer pickles it before the fit goes on)."""
    return t.detach().cpu().numpy()


class FitTimeline:
    """Writes the co-evolution of one fit to a USD timeline, in a writer process.

    Args:
        path: the ``.usdc`` file.
        every: iterations between samples (> 0).
        sim: the scene normalisation (:class:`wtopo.scene.Similarity`), internal -> caller's frame.
        cameras: training cameras, internal frame.
        timers: the fit's section timers (``"timeline"``: the host copy and the hand-over, and at the end the wait
            for the writer).
        max_surfels: the writer's ``max_surfels`` (``None``: its default).
    """

    def __init__(self, path: Path, every: int, sim, cameras: Sequence, timers, *, max_surfels: int | None = None):
        from ..io._timeline_process import TimelineProcess

        self.path = Path(path)
        self.every = int(every)
        self.sim = sim
        self.timers = timers
        self.failure: str | None = None
        """Why the timeline stopped (``None`` while it is written)."""
        self.writer = None
        kw = {} if max_surfels is None else {"max_surfels": int(max_surfels)}
        with self._guard("the start"):
            self.writer = TimelineProcess(path, **kw)
            self.writer.add_cameras([sim.to_world(c) for c in cameras])

    @contextlib.contextmanager
    def _guard(self, when: str) -> Iterator[None]:
        """An error inside the block (the writer's, or the sample's host copy) stops the timeline with a warning and
        the fit goes on; ``KeyboardInterrupt`` and ``SystemExit`` pass. A device error met in the host copy is the
        fit's as well, and the fit's next step raises it."""
        try:
            yield
        except Exception as e:  # noqa: BLE001 - any failure of the optional output
            self.failure = f"{type(e).__name__} at {when}: {e}"
            if self.writer is not None:
                self.writer.abort()
            self.writer = None
            warnings.warn(f"wtopo: the USD timeline stopped ({self.failure}); the fit goes on without it and writes "
                          f"no timeline.usdc", RuntimeWarning, stacklevel=4)

    @classmethod
    def open(cls, out_dir: Path | None, every: int, sim, cameras: Sequence, timers) -> FitTimeline | None:
        """A timeline in ``out_dir``, or ``None`` without a run directory or with ``every == 0``."""
        if out_dir is None or not every:
            return None
        return cls(out_dir / "timeline.usdc", every, sim, cameras, timers)

    def carry_over(self, it: int) -> None:
        """A resumed fit at iteration ``it``: the samples up to ``it`` of the timeline its earlier run wrote (where
        that run ended and wrote one) go first in this one, so that the file keeps the whole fit."""
        if self.writer is None or not self.path.exists():
            return
        with self.timers("timeline"), self._guard("the resume"):
            self.writer.carry_over(self.path, it)

    def sample(self, it: int, surfels: Surfels, proxy_mesh: ProxyResult | None) -> None:
        """Surfels (and the proxy mesh, when there is one) at time ``it``: copied to the host and handed to the
        writer now, authored while the fit goes on."""
        if self.writer is None:
            return
        s = surfels
        with self.timers("timeline"), self._guard(f"iteration {it}"):
            # only what the writer keeps leaves the device: its strided subset above its max_surfels (the same
            # indices it takes itself) and the SH's DC term (its splats keep degree 0, its instancer's colour is DC)
            n, keep = s.means.shape[0], self.writer.max_surfels
            idx = None
            if n > keep:
                idx = torch.from_numpy(np.linspace(0, n - 1, keep).round().astype(np.int64)).to(s.means.device)

            def take(t: torch.Tensor) -> np.ndarray:
                return _host(t if idx is None else t.detach()[idx])

            sim = self.sim
            with section("timeline_copy"):
                kw = {}
                if proxy_mesh is not None:
                    kw = {"mesh_verts": sim.to_world(_host(proxy_mesh.verts).astype(np.float64)),
                          "mesh_faces": _host(proxy_mesh.faces)}
                arrays = {"means": sim.to_world(take(s.means).astype(np.float64)), "quats": take(s.quats),
                          "scales": sim.length_to_world(take(s.scales).astype(np.float64)),
                          "opacities": take(s.opacities), "colors_or_sh": take(s.sh[:, :1]), **kw}
            with section("timeline_send"):
                self.writer.add_sample(int(it), **arrays)

    def abort(self) -> None:
        """End the writer after a failed fit; nothing is written (the file is written only at :meth:`close`), and
        no error of the writer is raised (the fit's own is on its way)."""
        if self.writer is not None:
            self.writer.abort()

    def close(self, mesh: trimesh.Trimesh | None) -> None:
        """Add the final mesh (internal frame; ``None``: none), wait for the writer and close the file."""
        if self.writer is None:
            return
        # an interrupt here reaches the fit's aborted_on_failure, which ends the writer
        with self.timers("timeline"), self._guard("the end"):
            if mesh is not None:
                self.writer.add_mesh("final", self.sim.to_world(np.asarray(mesh.vertices)), np.asarray(mesh.faces))
            with section("timeline_wait"):
                self.writer.close()


@contextlib.contextmanager
def aborted_on_failure(timeline: Callable[[], FitTimeline | None]) -> Iterator[None]:
    """Around a fit: when it raises, end the writer of its timeline (``timeline()``, opened inside the block;
    ``None``: none) with :meth:`FitTimeline.abort`; a fit that ends closes the timeline itself."""
    try:
        yield
    except BaseException:
        tl = timeline()
        if tl is not None:
            tl.abort()
        raise
