# SPDX-License-Identifier: Apache-2.0
"""The fit's render of a training view, forward and backward, replayed on CUDA as CUDA graphs.

At DTU's 384 px the rasterizer's kernels take about a millisecond of an iteration and its host side (binning, two
sorts, a dozen launches, allocations, the autograd bridge, the surfels' activations) about four
(``benchmarks/gpu.md``, lease ``u``). :func:`wtopo.rasterize._graphable.render_tensors` renders from tensors alone,
the camera included, so one capture serves every view of a size: ``torch.cuda.make_graphed_callables`` captures
the activations (``exp`` of the log scales, ``sigmoid`` of the opacity logits, the SH bands joined) and the render
as a forward and a backward graph per surfel count, pair capacity, image size and SH layout, and replays them
until a density step changes the count (every hundred iterations at most; the oldest graphs are dropped first). The
capacity a graph sorts for is the pair capacity rounded up to a step of a factor sqrt(2), so that the capacity's
small moves do not each capture again.

What stays eager around a replay: the view's inputs (cached tensors, copied into the graph's buffers), a zero
``shift`` [N, 2] whose gradient is the screen-space statistic (``RenderOutput.means2d``: here the zeros, not the
projected centres, which the fit never reads), and the pair count posted to the capacity. The outputs are the
graph's buffers, valid until the next replay (the fit reads them within the iteration); so are the gradients a
replay's backward hands to the parameters (torch takes them as the parameters' ``.grad`` without a copy, and the
next forward replay zeroes them: the fit drops its gradients after each step, and Adam copies them first).

A capture or replay that raises, a first replay whose images or gradients differ from the eager function's on the
same inputs, or captures more frequent than one per twenty renders (views of many sizes, a pair capacity that
swings), turn the graphs off for the rest of the fit, with a warning (:attr:`RasterGraphs.failure`). Off on the CPU
and under ``runtime.profile`` (whose sections synchronise, which a capture cannot hold).
"""

from __future__ import annotations

import warnings

import torch

from .. import _bridge
from .._graphs import make_graphed, on_device
from .._validate import trusted_values
from ..rasterize import RasterConfig, RenderOutput, _binning
from ..rasterize._graphable import Size, check_replay, pair_budget, render_tensors, view_inputs
from .surfels import Surfels

__all__ = ["RasterGraphs", "GRAPHS"]

GRAPHS = True
"""False: the fit renders eagerly on CUDA too (benchmarks, tests)."""
_KEPT = 4  # captured renders kept (views of two sizes, the current surfel count's and the one before)
_WARMUP = 2  # eager forward + backward runs before a capture (torch's side stream, the samples' copies)
_CHURN_CALLS, _CHURN_RATE = 200, 0.05  # after this many renders, more captures than this per render: off


def _function(size: Size, sh_degree: int, background: torch.Tensor, config: RasterConfig, pairs: int):
    """The captured function: the surfels' raw parameters and a view's tensors -> the render's tensors."""

    def render(means, quats, log_scales, opacity_logits, sh_dc, sh_rest, shift, rays, tables, row4, record):
        # the activations as Surfels computes them (the same operations: the same values)
        return render_tensors(means, quats, torch.exp(log_scales), torch.sigmoid(opacity_logits),
                              torch.cat([sh_dc, sh_rest], dim=1), shift, rays, tables, row4, record, size=size,
                              sh_degree=sh_degree, background=background, config=config, pairs=pairs)

    return render


class RasterGraphs:
    """Replayed renders of the fit's training views (see the module's docstring).

    Args:
        background: [3] background colour on the fit's device (kept: the graphs read it where it is).
        config: the fit's rasterizer settings (validated).
        make: what captures a function (``torch.cuda.make_graphed_callables``'s signature); tests pass one that
            returns the function itself, so that everything but the capture runs on any device.

    Attributes:
        failure: why the renders run eagerly, once a capture failed or disagreed (``None`` until then).
        captures: captures made so far.
    """

    def __init__(self, background: torch.Tensor, config: RasterConfig, *, make=None):
        self.background = background
        self.config = config
        self._make = make
        self._graphs: dict = {}
        self.failure: str | None = None
        self.captures = 0
        self.calls = 0

    def __call__(self, surfels: Surfels, camera) -> RenderOutput | None:
        """The render of ``camera``'s view of ``surfels`` from a replay (``RenderOutput`` with ``overflow`` set as
        the deferred-count path sets it), or ``None`` where the caller renders eagerly: graphs off or failed, no
        surfels, no pair capacity measured yet, no gradient wanted."""
        p = surfels.params
        means = p["means"]
        if (not GRAPHS or self.failure is not None or not torch.is_grad_enabled() or means.shape[0] == 0
                or not (means.is_cuda or self._make is not None)):
            return None
        capacity = _binning._pair_capacity(_bridge.warp_device(means.device))  # noqa: SLF001
        capacity.poll()
        if capacity.value == 0:  # the first deferred render measures it
            return None
        self.calls += 1
        if self.calls > _CHURN_CALLS and self.captures > _CHURN_RATE * self.calls:
            self._off(f"{self.captures} captures in {self.calls} renders (views of many sizes, or a pair count that "
                      f"swings)")
            return None
        dtype, device = means.dtype, means.device
        pairs = pair_budget(capacity.value, self.config.max_intersections)
        shift = torch.zeros(means.shape[0], 2, dtype=dtype, device=device, requires_grad=True)
        args = (means, p["quats"], p["log_scales"], p["opacity_logits"], p["sh_dc"], p["sh_rest"], shift,
                *view_inputs(camera, device, dtype, self.config))
        size = Size(camera.width, camera.height)
        key = (size, pairs, dtype, device, tuple(tuple(a.shape) for a in args), tuple(a.requires_grad for a in args))
        with on_device(device):
            graphed = self._graphs.get(key)
            if graphed is None:
                graphed = self._capture(key, args, _function(size, surfels.sh_degree, self.background, self.config,
                                                             pairs))
                if graphed is None:
                    return None
            try:
                rgb, alpha, depth, median, normal, dist, vis, radii, _, clip, overflow, count = graphed(*args)
            except Exception as e:  # noqa: BLE001 - a replay that fails leaves this render and the rest eager
                self._off(f"a replay failed: {type(e).__name__}: {e}")
                return None
        capacity.post(count, self.config.max_intersections)
        return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                            visibility=vis, radii=radii, means2d=shift, clip=clip, overflow=overflow)

    def _off(self, why: str) -> None:
        self.failure = why
        self._graphs.clear()
        warnings.warn(f"wtopo: the fit's renders run eagerly on this device: {why}", RuntimeWarning, stacklevel=4)

    def _capture(self, key, args: tuple, fn):
        """``fn`` captured for ``key`` and checked against itself run eagerly on ``args`` (images and gradients);
        ``None`` (graphs off) when the capture raises or disagrees. The oldest graphs go first (their memory)."""
        while len(self._graphs) >= _KEPT:
            self._graphs.pop(next(iter(self._graphs)))
        try:
            graphed = make_graphed(fn, args, warmup=_WARMUP, make=self._make)
            with trusted_values():
                check_replay(graphed, fn, args)
        except Exception as e:  # noqa: BLE001 - any failure leaves the renders eager
            self._off(f"{type(e).__name__}: {e}")
            return None
        self._graphs[key] = graphed
        self.captures += 1
        return graphed

