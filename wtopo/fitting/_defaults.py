# SPDX-License-Identifier: Apache-2.0
"""The plan's base budgets on a kind of device, for code that sizes work before a plan exists
(:mod:`wtopo.chunks` splits a scene by them)."""

from __future__ import annotations

from dataclasses import dataclass

from . import plan as _plan
from . import presets as _presets
from .config import Preset

__all__ = ["PlanDefaults", "plan_defaults"]


@dataclass(frozen=True)
class PlanDefaults:
    """The budgets :func:`~wtopo.fitting.plan.make_plan` starts from on one kind of device, for the fields
    a configuration leaves to the plan (``None``).

    Attributes:
        iterations: ``(warm-up, co-evolution)`` iterations of the device's base budget (the plan scales a
            CPU budget with the pixels to fit: :func:`~wtopo.fitting.plan.iteration_budget`).
        max_surfels: surfel cap (``runtime.max_surfels``).
        reinit_faces: most faces of the TSDF re-initialisation mesh, one surfel each (``tsdf.max_faces``).
        proxy_grid: the largest Poisson grid the plan picks, nodes per side (``mesh.resolution``).
        final_grid: the largest final TSDF grid the plan picks, voxels along the fusion box (``final.resolution``).
    """

    iterations: tuple[int, int]
    max_surfels: int
    reinit_faces: int
    proxy_grid: int
    final_grid: int


def plan_defaults(device, preset: Preset | str = Preset.BALANCED) -> PlanDefaults:
    """:class:`PlanDefaults` of ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"`` or a :class:`torch.device`) under
    ``preset`` (:mod:`wtopo.fitting.presets`): every CUDA device shares one budget."""
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    b = _presets.budget(preset, kind)
    return PlanDefaults(iterations=tuple(b.iterations), max_surfels=int(_plan._MAX_SURFELS[kind]),
                        reinit_faces=int(_plan._REINIT_FACES[kind]), proxy_grid=int(b.proxy_grid[1]),
                        final_grid=int(b.final_grid[1]))
