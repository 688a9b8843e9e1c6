# SPDX-License-Identifier: Apache-2.0
"""What every CUDA-graph capture needs: the fit's (the per-pixel terms, the render, Adam's update) and the public
rasterizer's replays (``wtopo.rasterize._replay``)."""

from __future__ import annotations

import contextlib
import gc
import warnings
from collections.abc import Iterator

import torch

from ._validate import trusted_values

__all__ = ["capture_forward", "collector_off", "make_graphed", "on_device"]


@contextlib.contextmanager
def collector_off() -> Iterator[None]:
    """The garbage collector off for the scope: a collection inside a capture could free a Warp array, a CUDA call
    that would invalidate the capture."""
    collect = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collect:
            gc.enable()


def make_graphed(fn, args: tuple, *, warmup: int, make=None):
    """``torch.cuda.make_graphed_callables(fn, samples, num_warmup_iters=warmup)`` on copies of ``args`` (each
    requiring a gradient where its original does; ``make``: a stand-in of that signature, for tests), with values
    trusted (an op's value check reads the device, which a capture cannot hold) and the collector off. torch's
    warning that the warm-up differentiates the copies (leaves made on the default stream) on its side stream is
    silenced: the copies are the capture's own, never a caller's leaves."""
    samples = tuple(a.detach().clone().requires_grad_(a.requires_grad) for a in args)
    with collector_off(), trusted_values(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="The AccumulateGrad node's stream does not match")
        return (make or torch.cuda.make_graphed_callables)(fn, samples, num_warmup_iters=warmup)


_side_streams: dict = {}


def _side_stream(device: torch.device):
    """One warm-up stream per device for every capture (each stream costs the bridge a Warp handle it keeps)."""
    device = torch.device(device)
    key = torch.cuda.current_device() if device.index is None else device.index
    if key not in _side_streams:
        _side_streams[key] = torch.cuda.Stream(device)
    return _side_streams[key]


def capture_forward(fn, args: tuple, *, warmup: int, capture=None) -> tuple:
    """``fn(*args)`` captured as one CUDA graph with autograd off: ``(replay, outputs)``, where ``replay()`` runs
    the graph again on whatever ``args``' memory then holds and leaves its results in ``outputs`` (the graph's
    own buffers, overwritten by each replay). ``warmup`` eager runs on a side stream come first (Warp's modules
    load, the caching allocator settles); values are trusted and the collector is off, as in :func:`make_graphed`.
    ``capture``: a stand-in of this signature (tests)."""
    if capture is not None:
        return capture(fn, args, warmup)
    device = args[0].device
    with collector_off(), trusted_values(), torch.no_grad():
        side = _side_stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                fn(*args)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            outs = tuple(fn(*args))
    return graph.replay, outs


def on_device(device: torch.device):
    """``torch.cuda.device(device)`` on CUDA (a capture checks torch's current device), else nothing."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()
