# SPDX-License-Identifier: Apache-2.0
"""The USD timeline of a fit: training cameras, surfels and proxy mesh every ``runtime.usd_every``
iterations, and the final mesh, all in the caller's frame (``out_dir/timeline.usdc``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from .proxy import ProxyResult
from .surfels import Surfels

__all__ = ["FitTimeline"]


class FitTimeline:
    """Writes the co-evolution of one fit to a USD timeline.

    Args:
        path: the ``.usdc`` file.
        every: iterations between samples (> 0).
        sim: the scene normalisation (:class:`wtopo.scene.Similarity`), internal -> caller's frame.
        cameras: training cameras, internal frame.
        timers: the fit's section timers (``"timeline"``).
    """

    def __init__(self, path: Path, every: int, sim, cameras: Sequence, timers):
        from ..io import TimelineWriter

        self.every = int(every)
        self.sim = sim
        self.timers = timers
        self.writer = TimelineWriter(path)
        self.writer.add_cameras([sim.to_world(c) for c in cameras])

    @classmethod
    def open(cls, out_dir: Path | None, every: int, sim, cameras: Sequence, timers) -> FitTimeline | None:
        """A timeline in ``out_dir``, or ``None`` without a run directory or with ``every == 0``."""
        if out_dir is None or not every:
            return None
        return cls(out_dir / "timeline.usdc", every, sim, cameras, timers)

    def sample(self, it: int, surfels: Surfels, proxy_mesh: ProxyResult | None) -> None:
        """Surfels (and the proxy mesh, when there is one) at time ``it``."""
        s, sim = surfels, self.sim
        kw = {}
        if proxy_mesh is not None:
            kw = {"mesh_verts": sim.to_world(proxy_mesh.verts.detach().cpu().double().numpy()),
                  "mesh_faces": proxy_mesh.faces.cpu().numpy()}
        with self.timers("timeline"):
            self.writer.add_sample(it, means=sim.to_world(s.means.detach().cpu().double().numpy()),
                                   quats=s.quats.detach().cpu().numpy(),
                                   scales=sim.length_to_world(s.scales.detach().cpu().double().numpy()),
                                   opacities=s.opacities.detach().cpu().numpy(),
                                   colors_or_sh=s.sh.detach().cpu().numpy(), **kw)

    def close(self, mesh: trimesh.Trimesh) -> None:
        """Add the final mesh (internal frame) and close the file."""
        with self.timers("timeline"):
            self.writer.add_mesh("final", self.sim.to_world(np.asarray(mesh.vertices)), np.asarray(mesh.faces))
            self.writer.close()
