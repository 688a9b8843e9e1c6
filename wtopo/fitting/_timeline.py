# SPDX-License-Identifier: Apache-2.0
"""The USD timeline of a fit: training cameras, surfels and proxy mesh every ``runtime.usd_every``
iterations, and the final mesh, all in the caller's frame (``out_dir/timeline.usdc``).

The fit only copies each sample to the host; one worker thread converts it to the caller's frame and
authors it into the stage while the fit goes on (at most one sample in flight, so at most one extra
sample in host memory). An error in the worker is raised at the next :meth:`FitTimeline.sample` or at
:meth:`FitTimeline.close`. The profile charges the worker's time to no section: on the CPU it slows whatever
section runs beside it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
import trimesh

from .proxy import ProxyResult
from .surfels import Surfels

__all__ = ["FitTimeline", "aborted_on_failure"]


def _copy(t: torch.Tensor) -> np.ndarray:
    """A host copy of ``t`` that the fit's later in-place updates cannot reach (on the CPU ``.cpu()`` would return
    the parameter's own memory, which the worker reads while the optimiser changes it)."""
    t = t.detach()
    return (t.clone() if t.device.type == "cpu" else t.cpu()).numpy()


class FitTimeline:
    """Writes the co-evolution of one fit to a USD timeline, on a worker thread.

    Args:
        path: the ``.usdc`` file.
        every: iterations between samples (> 0).
        sim: the scene normalisation (:class:`wtopo.scene.Similarity`), internal -> caller's frame.
        cameras: training cameras, internal frame.
        timers: the fit's section timers (``"timeline"``: the host copy, and the wait for the previous
            sample when it is still being written).
    """

    def __init__(self, path: Path, every: int, sim, cameras: Sequence, timers):
        from ..io import TimelineWriter

        self.every = int(every)
        self.sim = sim
        self.timers = timers
        self.writer = TimelineWriter(path)
        self.writer.add_cameras([sim.to_world(c) for c in cameras])
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="wtopo-timeline")
        self._pending: Future | None = None

    @classmethod
    def open(cls, out_dir: Path | None, every: int, sim, cameras: Sequence, timers) -> FitTimeline | None:
        """A timeline in ``out_dir``, or ``None`` without a run directory or with ``every == 0``."""
        if out_dir is None or not every:
            return None
        return cls(out_dir / "timeline.usdc", every, sim, cameras, timers)

    def _wait(self) -> None:
        """Wait for the sample in flight; re-raise its error."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def sample(self, it: int, surfels: Surfels, proxy_mesh: ProxyResult | None) -> None:
        """Surfels (and the proxy mesh, when there is one) at time ``it``: copied to the host now, written to
        the stage on the worker thread."""
        s = surfels
        with self.timers("timeline"):
            # only what the writer keeps leaves the device: its strided subset above its max_surfels (the same
            # indices it takes itself) and the SH's DC term (its splats keep degree 0, its instancer's colour is DC)
            n, keep = s.means.shape[0], self.writer.max_surfels
            idx = None
            if n > keep:
                idx = torch.from_numpy(np.linspace(0, n - 1, keep).round().astype(np.int64)).to(s.means.device)

            def take(t: torch.Tensor) -> np.ndarray:
                return _copy(t if idx is None else t.detach()[idx])

            host = {"means": take(s.means), "quats": take(s.quats), "scales": take(s.scales),
                    "opacities": take(s.opacities), "sh": take(s.sh[:, :1])}
            if proxy_mesh is not None:
                host["mesh_verts"] = _copy(proxy_mesh.verts)
                host["mesh_faces"] = _copy(proxy_mesh.faces)
            self._wait()
            self._pending = self._worker.submit(self._write, int(it), host)

    def _write(self, it: int, host: dict) -> None:
        sim = self.sim
        kw = {}
        if "mesh_verts" in host:
            kw = {"mesh_verts": sim.to_world(host["mesh_verts"].astype(np.float64)), "mesh_faces": host["mesh_faces"]}
        self.writer.add_sample(it, means=sim.to_world(host["means"].astype(np.float64)), quats=host["quats"],
                               scales=sim.length_to_world(host["scales"].astype(np.float64)),
                               opacities=host["opacities"], colors_or_sh=host["sh"], **kw)

    def abort(self) -> None:
        """Stop the worker after a failed fit: a sample not yet started is dropped, one in flight finishes, its
        error is not raised (the fit's own is on its way). Nothing is written: the file is written only at
        :meth:`close`."""
        self._pending = None
        self._worker.shutdown(wait=True, cancel_futures=True)

    def close(self, mesh: trimesh.Trimesh | None) -> None:
        """Wait for the last sample, add the final mesh (internal frame; ``None``: none) and close the file."""
        with self.timers("timeline"):
            try:
                self._wait()
                if mesh is not None:
                    self.writer.add_mesh("final", self.sim.to_world(np.asarray(mesh.vertices)),
                                         np.asarray(mesh.faces))
                self.writer.close()
            finally:
                self._worker.shutdown(wait=True)


@contextlib.contextmanager
def aborted_on_failure(timeline: Callable[[], FitTimeline | None]) -> Iterator[None]:
    """Around a fit: when it raises, stop the worker of its timeline (``timeline()``, opened inside the block;
    ``None``: none) with :meth:`FitTimeline.abort`; a fit that ends closes the timeline itself."""
    try:
        yield
    except BaseException:
        tl = timeline()
        if tl is not None:
            tl.abort()
        raise
