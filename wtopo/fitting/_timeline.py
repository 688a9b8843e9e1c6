# SPDX-License-Identifier: Apache-2.0
"""The USD timeline of a fit: training cameras, surfels and proxy mesh every ``runtime.usd_every``
iterations, and the final mesh, all in the caller's frame (``out_dir/timeline.usdc``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import trimesh

from .proxy import ProxyResult
from .surfels import Surfels

__all__ = ["FitTimeline", "vertex_normals"]


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals [V, 3] float32 of a mesh (verts [V, 3], faces [F, 3]) on its device, +z for a
    vertex no face uses: :class:`~wtopo.io.TimelineWriter`'s own normals, computed where the mesh is (a 400k-face
    proxy mesh's take tens of ms in NumPy on the host, every sample)."""
    v = verts.detach().double()
    f = faces.long()
    a = v[f[:, 0]]
    fn = torch.cross(v[f[:, 1]] - a, v[f[:, 2]] - a, dim=1)  # length: twice the area
    n = torch.zeros_like(v)
    for k in range(3):
        n.index_add_(0, f[:, k], fn)
    length = n.norm(dim=1, keepdim=True)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype, device=v.device)
    return torch.where(length > 0, n / length.clamp_min(1e-300), up).float()


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
            if proxy_mesh.verts.is_cuda:  # a scale and a shift to the caller's frame: the same unit normals
                kw["mesh_normals"] = vertex_normals(proxy_mesh.verts, proxy_mesh.faces).cpu().numpy()
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
