# SPDX-License-Identifier: Apache-2.0
"""Benchmark trilinear scatter against torch ``index_add_`` and time the DPSR Poisson solve.

What it shows: (1) ``wtopo.ops.scatter_trilinear`` of 10^6 points into 128^3 against two torch
peers measured in the same process: the full pure-torch op (corner indices + weights +
``index_add_``, ``tests/reference/scatter_trilinear.py``) and ``index_add_`` alone on precomputed
indices and weights; (2) ``poisson_indicator`` forward and backward at 64^3, 128^3, 256^3 with
time and peak memory. Peak memory is the resident set size (``/proc/self/statm``, sampled every
1 ms by a thread) above its level before the timed calls, in a fresh subprocess per resolution
after one warm-up call, so it counts torch, Warp and FFT buffers (tracemalloc would miss native
allocations); Linux only.

Hardware: any CPU (the project's machines: 2 cores); CUDA is used with ``--device cuda``.

Command::

    .venv/bin/python benchmarks/bench_scatter_poisson.py [--device cpu] [--repeats 5]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import threading
import time

import torch
from _from_tests import load  # beside this script

_ref = load("reference/scatter_trilinear.py")
scatter_trilinear_ref, trilinear_corners = _ref.scatter_trilinear_ref, _ref.trilinear_corners

from wtopo import _bridge  # noqa: E402
from wtopo.ops import poisson_indicator, scatter_trilinear  # noqa: E402
from wtopo.scatter import scatter_unchecked  # noqa: E402


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _interleaved(fns: dict, device: str, repeats: int) -> dict:
    """Median time of each callable, timed in alternation (round-robin) so load from other
    processes on a shared machine hits every contender alike."""
    for fn in fns.values():
        fn()  # warm-up (compiles kernels on the first call)
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            _sync(device)
            t0 = time.perf_counter()
            fn()
            _sync(device)
            times[k].append(time.perf_counter() - t0)
    return {k: sorted(v)[len(v) // 2] for k, v in times.items()}


class _PeakRss:
    """Peak resident set size above the level at entry, sampled from /proc/self/statm every 1 ms."""

    def __enter__(self):
        self._page = os.sysconf("SC_PAGE_SIZE")
        self.base = self.peak = self._rss()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()
        return self

    def _rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self._page

    def _poll(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(0.001)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())

    @property
    def mib(self) -> float:
        return (self.peak - self.base) / 2 ** 20


def _sphere(n: int, device: str):
    g = torch.Generator().manual_seed(0)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    return (0.5 + 0.35 * d).to(device), d.to(device), torch.ones(n, device=device)


def bench_scatter(device: str, repeats: int, n: int = 1_000_000, resolution: int = 128) -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(n, 3, generator=g).to(device)
    print(f"scatter_trilinear: {n} points -> {resolution}^3, device {device}, "
          f"{_bridge.cpu_threads()} CPU threads")
    for channels in (1, 3):
        vals = torch.randn(n, channels, generator=g).to(device)
        idx, w = trilinear_corners(pts, resolution)
        keep = idx >= 0
        flat_idx = idx[keep]
        contrib = (w.unsqueeze(-1) * vals.unsqueeze(1))[keep]

        def index_add_only(channels=channels, flat_idx=flat_idx, contrib=contrib):
            torch.zeros(resolution ** 3, channels, device=device).index_add_(0, flat_idx, contrib)

        t = _interleaved({"op": lambda vals=vals: scatter_trilinear(pts, vals, resolution),
                          "raw": lambda vals=vals: scatter_unchecked(pts, vals, resolution),
                          "ref": lambda vals=vals: scatter_trilinear_ref(pts, vals, resolution),
                          "index_add": index_add_only}, device, repeats)
        print(f"  C={channels}: wtopo {t['op'] * 1e3:7.1f} ms (validation included; {t['raw'] * 1e3:.1f} ms "
              f"without) | torch full reference {t['ref'] * 1e3:7.1f} ms -> ratio {t['ref'] / t['op']:.2f}x | "
              f"index_add_ alone {t['index_add'] * 1e3:7.1f} ms -> ratio {t['index_add'] / t['op']:.2f}x "
              "(ratio > 1: wtopo faster)")


def _poisson_child(resolution: int, device: str, repeats: int, n: int) -> dict:
    pts, nrm, w = _sphere(n, device)
    pts.requires_grad_()
    nrm.requires_grad_()

    def step():
        chi = poisson_indicator(pts, nrm, w, resolution, sigma=1.0, padding=0.1).chi
        _sync(device)
        t1 = time.perf_counter()
        chi.backward(torch.ones_like(chi) / chi.numel())
        _sync(device)
        return t1, time.perf_counter()

    step()  # compiles kernels and builds the cached spectral operator
    gc.collect()
    fwd, bwd = [], []
    with _PeakRss() as mem:
        for _ in range(repeats):
            _sync(device)
            t0 = time.perf_counter()
            t1, t2 = step()
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
    fwd.sort()
    bwd.sort()
    return {"resolution": resolution, "forward_ms": fwd[len(fwd) // 2] * 1e3,
            "backward_ms": bwd[len(bwd) // 2] * 1e3, "peak_rss_mib": mem.mib}


def bench_poisson(device: str, repeats: int, n: int = 100_000) -> None:
    print(f"poisson_indicator: {n} points on a sphere, sigma 1 voxel, padding 0.1, device {device}; "
          "peak = sampled peak RSS above the level before the timed calls, fresh process per R")
    print("  R     forward ms  backward ms  peak MiB")
    for r in (64, 128, 256):
        out = subprocess.run([sys.executable, os.path.abspath(__file__), "--poisson-child", str(r), "--device",
                              device, "--repeats", str(repeats), "--points", str(n)],
                             capture_output=True, text=True, check=True)
        res = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"  {r:<5d} {res['forward_ms']:10.1f}  {res['backward_ms']:11.1f}  {res['peak_rss_mib']:8.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--points", type=int, default=100_000, help="points for the Poisson benchmark")
    parser.add_argument("--poisson-child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.poisson_child:
        print(json.dumps(_poisson_child(args.poisson_child, args.device, args.repeats, args.points)))
        return
    bench_scatter(args.device, args.repeats)
    bench_poisson(args.device, args.repeats, args.points)


if __name__ == "__main__":
    main()
