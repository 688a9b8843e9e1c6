# SPDX-License-Identifier: Apache-2.0
"""The fit's render of a training view, forward and backward, replayed on CUDA as CUDA graphs.

At DTU's 384 px the rasterizer's kernels take about a millisecond of an iteration and its host side (binning, two
sorts, a dozen launches, allocations, the autograd bridge, the surfels' activations) about four
(``benchmarks/gpu.md``, lease ``u``). :func:`wtopo.rasterize._graphable.render_tensors` renders from tensors alone,
the camera included, so one capture serves every view of a size: ``torch.cuda.make_graphed_callables`` captures
the activations (``exp`` of the log scales, ``sigmoid`` of the opacity logits, the SH bands joined) and the render
as a forward and a backward graph per surfel count, pair capacity, image size and SH layout, and replays them
until a density step changes the count (every hundred iterations at most; the previous graphs are dropped).

What stays eager around a replay: the view's inputs (cached tensors, copied into the graph's buffers), a zero
``shift`` [N, 2] whose gradient is the screen-space statistic (``RenderOutput.means2d``: here the zeros, not the
projected centres, which the fit never reads), and the pair count posted to the capacity. The outputs are the
graph's buffers, valid until the next replay (the fit reads them within the iteration).

A capture that raises, or whose first replay differs from the eager function on the same inputs, turns the graphs
off for the rest of the fit, with a warning (:attr:`RasterGraphs.failure`). Off on the CPU and under
``runtime.profile`` (whose sections synchronise, which a capture cannot hold).
"""

from __future__ import annotations

import warnings

import torch

from .. import _bridge
from .._validate import trusted_values
from ..rasterize import RasterConfig, RenderOutput, _binning
from ..rasterize._graphable import Size, render_tensors, view_inputs
from .surfels import Surfels

__all__ = ["RasterGraphs", "GRAPHS"]

GRAPHS = True
"""False: the fit renders eagerly on CUDA too (benchmarks, tests)."""
_KEPT = 2  # captured renders kept (the current surfel count's, and the one before)
_CHECK_RTOL, _CHECK_ATOL = 1e-5, 1e-6  # a first replay farther than this from the eager render turns graphs off
_WARMUP = 2  # eager forward + backward runs before a capture (torch's side stream, the samples' copies)


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
        dtype, device = means.dtype, means.device
        shift = torch.zeros(means.shape[0], 2, dtype=dtype, device=device, requires_grad=True)
        args = (means, p["quats"], p["log_scales"], p["opacity_logits"], p["sh_dc"], p["sh_rest"], shift,
                *view_inputs(camera, device, dtype, self.config))
        size = Size(camera.width, camera.height)
        key = (size, capacity.value, dtype, device, tuple(tuple(a.shape) for a in args),
               tuple(a.requires_grad for a in args))
        graphed = self._graphs.get(key)
        if graphed is None:
            graphed = self._capture(key, args, _function(size, surfels.sh_degree, self.background, self.config,
                                                         capacity.value))
            if graphed is None:
                return None
        rgb, alpha, depth, median, normal, dist, vis, radii, _, clip, overflow, count = graphed(*args)
        capacity.post(count, self.config.max_intersections)
        return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, median_depth=median, normal=normal, distortion=dist,
                            visibility=vis, radii=radii, means2d=shift, clip=clip, overflow=overflow)

    def _capture(self, key, args: tuple, fn):
        """``fn`` captured for ``key`` and checked against itself run eagerly on ``args``; ``None`` (graphs off)
        when the capture raises or disagrees."""
        make = self._make or torch.cuda.make_graphed_callables
        samples = tuple(a.detach().clone().requires_grad_(a.requires_grad) for a in args)
        try:
            with trusted_values(), warnings.catch_warnings():
                # the warm-up differentiates the samples (leaves made on the default stream) on torch's side stream
                warnings.filterwarnings("ignore", message="The AccumulateGrad node's stream does not match")
                graphed = make(fn, samples, num_warmup_iters=_WARMUP)
                with torch.no_grad():
                    want = fn(*args)
                    got = graphed(*(a.detach() for a in args))
                    for k, (a, b) in enumerate(zip(got, want)):
                        if not torch.allclose(a.double(), b.double(), rtol=_CHECK_RTOL, atol=_CHECK_ATOL):
                            raise RuntimeError(f"output {k} of a replay differs from the eager render by "
                                               f"{float((a.double() - b.double()).abs().max()):.3g}")
        except Exception as e:  # noqa: BLE001 - any failure leaves the renders eager
            self.failure = f"{type(e).__name__}: {e}"
            self._graphs.clear()
            warnings.warn(f"wtopo: the fit's renders run eagerly on this device: {self.failure}", RuntimeWarning,
                          stacklevel=3)
            return None
        while len(self._graphs) >= _KEPT:
            self._graphs.pop(next(iter(self._graphs)))
        self._graphs[key] = graphed
        self.captures += 1
        return graphed
