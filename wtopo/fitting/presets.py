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
    mesh_every: int = 1
    polish: float = 0.5


@dataclass(frozen=True)
class _Rates:
    """The model of :func:`expected_seconds` on one kind of device (every preset shares it), in seconds on the
    reference device.

    Attributes:
        fixed_s: outside the iterations (initialisation, re-initialisation, final mesh).
        iteration_s: per iteration, whatever the view's size ...
        megapixel_s: ... plus this per megapixel of the view that the fit covers (its mask's pixels; every pixel
            without masks, where the surfels fill the frame).
        proxy_s: what a proxy-mesh build adds to its iteration (the proxy, its terms and their backward).
        stereo_s: what the plane-sweep stereo adds where it gives the initial surfels (a scene without points).
    """

    fixed_s: float
    iteration_s: float
    megapixel_s: float
    proxy_s: float
    stereo_s: float


_REFERENCE_CORES = 2  # the CPU timings below were measured on 2 cores; more cores scale them down
# The time model, fitted to fits timed with nothing else on the machine (wall time of wtopo.fit, images to mesh):
# CPU: benchmarks/error_vs_runtime.py at 0ce9513 (2026-12-08, 2 cores): the bunny, ring_capsule (objects, 21 % and
# 17 % of their 128-px views masked in) and bunny_room (a scene, its surfels from stereo) at the three presets and
# at 0.5x and 1.5x balanced's iterations, 15 fits, every one within 13 % of the model (a second run at 4e08b70:
# within 20 %). CUDA (one H100 alone, benchmarks/peers.md): DTU scan24 at the default, 5,000 iterations of
# 137k-pixel views without the loop, 27-32 s of which 11 s outside the iterations (benchmarks/gpu.md); the bowl,
# the mug and bunny64, 64 views of 512 px (21-35 % masked in), 6,000 iterations of which 2,000 build the proxy,
# 87-118 s. A proxy build then costs about 30 ms, a plain iteration 3-4 ms.
_RATES = {"cpu": _Rates(8.0, 0.022, 5.8, 0.054, 12.7), "cuda": _Rates(11.0, 0.0028, 0.010, 0.031, 0.0)}
# polish: the CPU balanced bunny (two seeds) gains 0.07-0.10 dB of held-out PSNR at 0.5, 0.15-0.17 at 1 (the same
# iterations with the loop on: 0.01-0.05); at best 0.09-0.10 at 0.25-0.5 and 0.05 at 1 (design/decisions.md,
# "Kept: a photometric polish").
_BUDGETS = {
    ("cpu", Preset.FAST): Budget((150, 150), 128, (48, 48), (64, 128), mesh_every=2, polish=0.0),
    ("cpu", Preset.BALANCED): Budget((400, 400), 256, (64, 64), (96, 192), mesh_every=2),
    ("cpu", Preset.BEST): Budget((800, 800), 256, (64, 64), (96, 192)),
    ("cuda", Preset.FAST): Budget((1500, 1000), 512, (128, 192), (192, 512), polish=0.0),
    ("cuda", Preset.BALANCED): Budget((3000, 2000), 1024, (128, 256), (192, 768)),
    ("cuda", Preset.BEST): Budget((6000, 4000), 1024, (128, 256), (192, 768)),
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


def expected_seconds(preset: Preset | str, device, iterations: int, pixels_per_view: float, *,
                     proxy_builds: int = 0, stereo: bool = False) -> float:
    """About how long a fit takes under ``preset`` on ``device`` [s]: the device's fixed time (more where
    ``stereo`` gives the initial surfels), ``iterations`` times its time per iteration on views of which the fit
    covers ``pixels_per_view`` pixels (a mask's pixels; every pixel without masks), and ``proxy_builds`` times a
    proxy-mesh build; on a CPU scaled by ``(2 / cores) ** 0.75`` for more cores than the reference's 2. A planning
    figure, not a promise: surfel counts, the grids and other load on the machine move it. ``preset`` is checked
    (:func:`budget`); the rates are the device's, its iterations the caller's."""
    budget(preset, device)
    r = _RATES[_kind(device)]
    t = (r.fixed_s + (r.stereo_s if stereo else 0.0) + max(0, int(proxy_builds)) * r.proxy_s
         + max(0, int(iterations)) * (r.iteration_s + r.megapixel_s * float(pixels_per_view) / 1e6))
    if _kind(device) == "cpu":
        import torch

        cores = max(1, min(torch.get_num_threads(), os.cpu_count() or 1))
        t *= (_REFERENCE_CORES / max(cores, _REFERENCE_CORES)) ** 0.75
    return float(t)
