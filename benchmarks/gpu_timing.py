# SPDX-License-Identifier: Apache-2.0
"""CUDA timing helpers of the GPU benchmarks (``bench_rasterize_gpu.py``, ``bench_losses.py``): CUDA-event latency of
one call from an idle device, the pipelined time of calls back to back, and the kernels of a call by device time."""

from __future__ import annotations

import statistics
import time

import torch


def cuda_event() -> torch.cuda.Event:
    """A CUDA event that records time."""
    return torch.cuda.Event(enable_timing=True)


def time_latency(fn, warmup: int, repeats: int) -> dict:
    """Each call from an idle device: median / min CUDA-event ms from before the call to its last kernel, host ms."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    dev, host = [], []
    for _ in range(repeats):
        e0, e1 = cuda_event(), cuda_event()
        e0.record()
        t0 = time.perf_counter()
        fn()
        t1 = time.perf_counter()
        e1.record()
        torch.cuda.synchronize()
        dev.append(e0.elapsed_time(e1))
        host.append(1e3 * (t1 - t0))
    return {"ms": statistics.median(dev), "ms_min": min(dev), "host_ms": statistics.median(host)}


def time_pipelined(fn, warmup: int, repeats: int) -> dict:
    """``repeats`` calls back to back between two events (no synchronisation in between): ms per call."""
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    e0, e1 = cuda_event(), cuda_event()
    e0.record()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    e1.record()
    torch.cuda.synchronize()
    return {"ms": e0.elapsed_time(e1) / repeats, "wall_ms": 1e3 * (time.perf_counter() - t0) / repeats}


def profile_kernels(fn, label: str, calls: int = 5, top: int = 8, per: int = 1) -> list:
    """CUDA kernel times of ``calls`` calls of ``fn`` (torch.profiler, CUPTI: Warp's kernels included), printed,
    per call or, with ``per``, per ``1 / per`` of a call (``fn`` doing ``per`` iterations)."""
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()
    rows = []
    for e in prof.key_averages():
        us = getattr(e, "device_time_total", None)
        if us is None:
            us = e.cuda_time_total
        if us > 0:
            rows.append((e.key, us / calls / per / 1e3, e.count / calls / per))
    rows.sort(key=lambda r: -r[1])
    total = sum(r[1] for r in rows)
    print(f"\nkernel profile, {label}: {total:.3f} ms of kernels per {'call' if per == 1 else 'iteration'}")
    for key, ms, cnt in rows[:top]:
        print(f"  {ms:8.3f} ms  x{cnt:<5.3g} {key[:90]}")
    return [{"kernel": k, "ms_per_call": ms, "launches_per_call": c} for k, ms, c in rows[:top]] + [
        {"kernel": "total", "ms_per_call": total}]
