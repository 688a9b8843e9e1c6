# SPDX-License-Identifier: Apache-2.0
"""Quality presets: the budgets the stage plan starts from, one point each on the error-against-time front.

``FitConfig.preset`` (``--preset``) picks one of :class:`~wtopo.fitting.config_kinds.Preset`; the plan
(:func:`~wtopo.fitting.plan.make_plan`) takes its iterations, image-size cap and grids from the preset's
:class:`Budget` on the fit's kind of device, and a field the configuration sets still wins. The values
and the figures behind them are in ``design/decisions.md`` ("presets"); ``benchmarks/error_vs_runtime.py``
measures the error-against-time front over a suite of scenes with the presets marked.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from .config_kinds import Preset

__all__ = ["Budget", "budget", "expected_seconds", "Preset"]


@dataclass(frozen=True)
class Budget:
    """What one preset gives the plan on one kind of device.

    Attributes:
        iterations: ``(warm-up, co-evolution)`` base iterations (the CPU plan scales them up for captures
            with more pixels to fit: :func:`~wtopo.fitting.plan.iteration_budget`).
        max_side: longest training-image side [px]; larger photographs are resized (never upsampled).
        proxy_grid: ``(min, max)`` Poisson nodes per side of the proxy mesh (the plan picks within it from
            the pixel footprint).
        final_grid: ``(min, max)`` TSDF voxels along the final fusion box.
        fixed_s: the model of :func:`expected_seconds`: seconds outside the iterations (initialisation,
            re-initialisation, final mesh) on the reference device.
        iteration_s: seconds per iteration on the reference device, whatever the view's size ...
        megapixel_s: ... plus these seconds per megapixel of the trained view.
        mesh_every: the co-evolution rebuilds the proxy mesh and applies its terms on every ``mesh_every``-th
            iteration, weighted ``mesh_every`` (the same mean gradient for ``1 / mesh_every`` of the proxy's
            time: on a CPU a proxy iteration costs about twice a photometric one).
        polish: after a proxy-mesh loop, photometric iterations before the final mesh as a share of the
            co-evolution's (:class:`~wtopo.fitting.config.PolishConfig`): the surfels' held-out PSNR, and a mesh
            fused from surfels the proxy no longer pulls, for time.
    """

    iterations: tuple[int, int]
    max_side: int
    proxy_grid: tuple[int, int]
    final_grid: tuple[int, int]
    fixed_s: float
    iteration_s: float
    megapixel_s: float
    mesh_every: int = 1
    polish: float = 0.5


_REFERENCE_CORES = 2  # the CPU timings below were measured on 2 cores; more cores scale them down
# CPU (2 idle cores, 2026-12-02, the fit without Open3D): the bunny's fast fit (150 + 150 iterations of 128 px
# views) took 21.7-22.0 s, about 6 s of it outside the iterations; balanced (400 + 400) 54.7-57.1 s, about 9 s
# outside them; best (800 + 800, every co-evolution iteration building the proxy) 114 s. CUDA (one H200, alone, warm
# kernel cache): DTU at the balanced default (5,000 iterations of 137k-pixel views, no mesh loop) 101 s with 20 s
# outside the iterations (2026-12-04, benchmarks/gpu.md), the 64-view chair (262k-pixel views, the mesh loop) 127 s
# (2026-12-03, benchmarks/peers.md): 13 ms an iteration plus 32 ms per megapixel of view; fast and best scale the
# iterations and keep the rates until a GPU front is measured. The CUDA rates date from before the GPU speed work:
# DTU now takes 27 s on one H100 (2026-12-06, benchmarks/gpu.md), so they overstate a CUDA fit about fourfold
# until a fit with the mesh loop is timed alone and they are measured again.
# polish: the CPU balanced bunny (two seeds) gains 0.07-0.10 dB of held-out PSNR at 0.5, 0.15-0.17 at 1 (the same
# iterations with the loop on: 0.01-0.05); at best 0.09-0.10 at 0.25-0.5 and 0.05 at 1 (design/decisions.md,
# "Kept: a photometric polish").
_BUDGETS = {
    ("cpu", Preset.FAST): Budget((150, 150), 128, (48, 48), (64, 128), 6.0, 0.0, 3.3, mesh_every=2, polish=0.0),
    ("cpu", Preset.BALANCED): Budget((400, 400), 256, (64, 64), (96, 192), 9.0, 0.010, 3.0, mesh_every=2),
    ("cpu", Preset.BEST): Budget((800, 800), 256, (64, 64), (96, 192), 9.0, 0.029, 2.2),
    ("cuda", Preset.FAST): Budget((1500, 1000), 512, (128, 192), (192, 512), 12.0, 0.013, 0.032, polish=0.0),
    ("cuda", Preset.BALANCED): Budget((3000, 2000), 1024, (128, 256), (192, 768), 20.0, 0.013, 0.032),
    ("cuda", Preset.BEST): Budget((6000, 4000), 1024, (128, 256), (192, 768), 20.0, 0.013, 0.032),
}


def _kind(device) -> str:
    return "cuda" if str(getattr(device, "type", device)).startswith("cuda") else "cpu"


def budget(preset: Preset | str, device) -> Budget:
    """The :class:`Budget` of ``preset`` (a :class:`Preset` or its name) on ``device`` (``"cpu"``, ``"cuda:0"``,
    a :class:`torch.device`; every CUDA device shares one budget).

    Raises:
        ValueError: ``preset`` is not ``"fast"``, ``"balanced"`` or ``"best"``.
    """
    try:
        p = Preset(preset)
    except ValueError:
        raise ValueError(f"preset must be one of {[p.value for p in Preset]}, got {preset!r}") from None
    return _BUDGETS[(_kind(device), p)]


def expected_seconds(preset: Preset | str, device, iterations: int, pixels_per_view: float) -> float:
    """About how long a fit of ``iterations`` iterations on views of ``pixels_per_view`` trained pixels takes
    under ``preset`` on ``device`` [s]: the preset's fixed time plus ``iterations`` times its time per
    iteration, on a CPU scaled by ``(2 / cores) ** 0.75`` for more cores than the reference's 2. A planning
    figure, not a promise: surfel counts, the scene and other load on the machine move it."""
    b = budget(preset, device)
    t = b.fixed_s + max(0, int(iterations)) * (b.iteration_s + b.megapixel_s * float(pixels_per_view) / 1e6)
    if _kind(device) == "cpu":
        import torch

        cores = max(1, min(torch.get_num_threads(), os.cpu_count() or 1))
        t *= (_REFERENCE_CORES / max(cores, _REFERENCE_CORES)) ** 0.75
    return float(t)
