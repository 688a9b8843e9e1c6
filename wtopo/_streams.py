# SPDX-License-Identifier: Apache-2.0
"""The bridge's streams: Warp's launches on torch's current CUDA stream, and torch's graph captures registered
with Warp. :mod:`wtopo._bridge` re-exports :func:`torch_stream` and :func:`registered_capture`."""

from __future__ import annotations

import collections
import contextlib

import torch
import warp as wp

_streams: dict = {}


def _warp_stream(device) -> wp.Stream:
    """Warp's handle of torch's current stream on ``device``, made once per stream.

    ``wp.stream_from_torch`` registers the stream with Warp's runtime at every call and unregisters it when the
    handle goes (two runtime calls per scope, four per op); the cached handle keeps the torch stream alive.
    """
    ts = torch.cuda.current_stream(device)
    key = (ts.device_index, ts.cuda_stream)
    ws = _streams.get(key)
    if ws is None:
        ws = _streams[key] = wp.stream_from_torch(ts)
    return ws


_captured: collections.deque = collections.deque(maxlen=256)  # Warp's handles of registered captures (see below)


@contextlib.contextmanager
def registered_capture(device: torch.device):
    """While torch captures a CUDA graph on ``device``'s current stream, register that capture with Warp for the
    scope (``wp.capture_begin(external=True)``): Warp's radix sort then takes its scratch memory inside the graph
    (freed with it) instead of a cache that a later, larger eager sort frees under the graph, or a buffer leaked
    per capture with a warning, and Warp retains the modules the capture launches (its handle is kept). A no-op
    when nothing is being captured, or inside a scope that registered the capture already."""
    if device.type != "cuda" or not torch.cuda.is_current_stream_capturing():
        yield
        return
    ws = _warp_stream(device)
    if ws.device.captures.get(ws) is not None:
        yield
        return
    wp.capture_begin(stream=ws, external=True, capture_mode=wp.CaptureMode.GLOBAL)
    ok = False
    try:
        yield
        ok = True
    finally:
        try:
            _captured.append(wp.capture_end(stream=ws))
        except Exception:
            if ok:  # an error of the scope itself takes precedence
                raise


@contextlib.contextmanager
def _on_torch_stream(wdev, device):
    """Scope Warp to ``wdev`` and, on CUDA, to torch's current stream on ``device``."""
    with wp.ScopedDevice(wdev):
        if wdev.is_cuda:
            # entering waits for Warp's previous stream (work Warp queued outside any scope), except while torch
            # captures a CUDA graph on this stream: a capture may not wait for work outside it, and none is there
            with wp.ScopedStream(_warp_stream(device), sync_enter=not torch.cuda.is_current_stream_capturing()):
                yield
        else:
            yield


def torch_stream(wdev, device):
    """Context: Warp launches on ``wdev`` and, on CUDA, on torch's current stream of ``device``.

    For launches an op makes outside :func:`apply` (discrete set-up such as binning), so they are
    ordered with the torch ops around them.
    """
    return _on_torch_stream(wdev, device)
