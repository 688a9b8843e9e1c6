# SPDX-License-Identifier: Apache-2.0
"""Benchmark: ``wtopo.ops.marching_cubes`` forward + backward against skimage's forward alone.

Field: a perturbed sphere SDF on ``[-1, 1]^3`` (float32).  For each resolution the three
extractors run interleaved in one process, so machine load hits them alike; the script prints
the best and median wall times and their ratios against ``skimage.measure.marching_cubes``
(forward only, the peer the issue names) and Warp's stock ``warp.geometry.IsoSurfaceMarchingCubes``
(forward + backward on a tape).  Peak memory is measured in a fresh child process per resolution
as the rise of the peak resident set size over a run of wtopo forward + backward.

Run: ``.venv/bin/python benchmarks/bench_marching_cubes.py [--sizes 64 128 256]
[--repeats 15] [--no-warp] [--device cuda:0]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

import numpy as np
import torch


def make_field(n: int) -> torch.Tensor:
    """A sphere SDF of radius 0.6 with a smooth ripple, ``n^3`` float32 nodes on ``[-1, 1]^3``."""
    x = torch.linspace(-1.0, 1.0, n)
    gx, gy, gz = torch.meshgrid(x, x, x, indexing="ij")
    f = (gx * gx + gy * gy + gz * gz).sqrt() - 0.6 + 0.05 * torch.sin(7 * gx) * torch.cos(5 * gy)
    return f.contiguous()


def run_wtopo(leaf: torch.Tensor) -> tuple[int, int]:
    """One forward + backward of wtopo's marching cubes on a leaf tensor; returns (vertices, faces)."""
    from wtopo.ops import marching_cubes

    verts, faces = marching_cubes(leaf, lower=(-1, -1, -1), upper=(1, 1, 1))
    torch.autograd.grad(verts.sum(), leaf)
    return verts.shape[0], faces.shape[0]


def run_skimage(field_np: np.ndarray) -> tuple[int, int]:
    """Run skimage's Lewiner marching cubes, forward only."""
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(field_np, 0.0)
    return verts.shape[0], faces.shape[0]


def run_warp(field: torch.Tensor) -> tuple[int, int]:
    """Warp's stock marching cubes, forward + backward through a tape."""
    import warp as wp
    from warp.geometry import IsoSurfaceMarchingCubes

    wf = wp.from_torch(field.detach().clone(), requires_grad=True)
    tape = wp.Tape()
    with tape:
        verts, tris = IsoSurfaceMarchingCubes.extract(wf, 0.0, lower=(-1, -1, -1), upper=(1, 1, 1))
    verts.grad.fill_(1.0)
    tape.backward()
    return verts.shape[0], tris.shape[0] // 3


_SYNC = None  # set to a callable that waits for the device (CUDA runs)


def _time(fn, *args) -> float:
    if _SYNC:
        _SYNC()
    t = time.perf_counter()
    fn(*args)
    if _SYNC:
        _SYNC()
    return time.perf_counter() - t


def run_wtopo_forward(field: torch.Tensor) -> tuple[int, int]:
    """Run wtopo's marching cubes, forward only (no autograd graph)."""
    from wtopo.ops import marching_cubes

    verts, faces = marching_cubes(field, lower=(-1, -1, -1), upper=(1, 1, 1))
    return verts.shape[0], faces.shape[0]


def main_device(args) -> None:
    """CUDA timing: wtopo forward and forward + backward on the device, skimage (CPU) as the peer."""
    global _SYNC
    dev = args.device
    _SYNC = lambda: torch.cuda.synchronize(dev)  # noqa: E731
    print(f"device {torch.cuda.get_device_name(dev)}, field: perturbed sphere SDF, float32; times: min / median")
    print(f"{'n':>5} {'V':>8} {'F':>8} | {'wtopo fwd':>18} {'wtopo f+b':>18} | "
          f"{'skimage f (CPU)':>15} | {'peak MiB':>8}")
    for n in args.sizes:
        field = make_field(n)
        sk = [_time(run_skimage, field.numpy()) for _ in range(3)]
        field = field.to(dev)
        leaf = field.clone().requires_grad_(True)
        nv, nf = run_wtopo_forward(field)
        run_wtopo(leaf)
        torch.cuda.reset_peak_memory_stats(dev)
        fwd = [_time(run_wtopo_forward, field) for _ in range(args.repeats)]
        fb = [_time(run_wtopo, leaf) for _ in range(args.repeats)]
        import warp as wp

        peak = torch.cuda.max_memory_allocated(dev) / 2**20 + wp.get_mempool_used_mem_high(dev) / 2**20
        print(f"{n:>5} {nv:>8} {nf:>8} | {min(fwd) * 1e3:7.3f} / {statistics.median(fwd) * 1e3:6.3f} ms "
              f"{min(fb) * 1e3:7.3f} / {statistics.median(fb) * 1e3:6.3f} ms | {min(sk) * 1e3:12.1f} ms | "
              f"{peak:8.1f}")


def peak_memory_child(n: int) -> None:
    """Child process: print the peak-RSS rise (MiB) of one wtopo forward + backward at ``n^3``."""

    def status(key):
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024.0
        return float("nan")

    field = make_field(n).requires_grad_(True)
    run_wtopo(make_field(8).requires_grad_(True))  # compile / load kernels before the baseline
    import ctypes

    ctypes.CDLL("libc.so.6").malloc_trim(0)  # hand freed temporaries back, so reuse cannot hide allocations
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # reset the peak (VmHWM) to the current resident set: field creation's temporaries
    before = status("VmRSS:")
    run_wtopo(field)
    print(json.dumps({"peak_rise_mib": status("VmHWM:") - before, "field_mib": field.numel() * 4 / 2**20}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--no-warp", action="store_true", help="skip Warp's stock IsoSurfaceMarchingCubes")
    parser.add_argument("--torch-threads", type=int, default=None,
                        help="torch.set_num_threads for the run (default: torch's own choice)")
    parser.add_argument("--memory-child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda:N: time wtopo on that device "
                        "(peak = torch's peak + Warp's pool high-water mark instead of RSS)")
    args = parser.parse_args()
    if args.device != "cpu":
        main_device(args)
        return
    if args.memory_child is not None:
        peak_memory_child(args.memory_child)
        return

    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    print(f"torch threads {torch.get_num_threads()}, field: perturbed sphere SDF, float32")
    print(f"{'n':>5} {'V':>8} {'F':>8} | {'wtopo f+b':>10} {'skimage f':>10} {'ratio':>6} {'med.ratio':>9} | "
          f"{'warp f+b':>9} {'warp/wtopo':>10} | {'peak MiB':>8}")
    for n in args.sizes:
        field = make_field(n)
        field_np = field.numpy()
        leaf = field.clone().requires_grad_(True)
        nv, nf = run_wtopo(leaf)
        sv, sf = run_skimage(field_np)
        use_warp = not args.no_warp
        if use_warp:
            run_warp(field)
        ours, sk, warp_t = [], [], []
        for _ in range(args.repeats):
            ours.append(_time(run_wtopo, leaf))
            sk.append(_time(run_skimage, field_np))
            if use_warp and len(warp_t) < max(3, args.repeats // 3):
                warp_t.append(_time(run_warp, field))
        pair = statistics.median(o / s for o, s in zip(ours, sk))
        mem = subprocess.run([sys.executable, __file__, "--memory-child", str(n)], capture_output=True, text=True,
                             check=True)
        peak = json.loads(mem.stdout.strip().splitlines()[-1])["peak_rise_mib"]
        warp_s = f"{min(warp_t) * 1e3:8.1f}ms {min(warp_t) / min(ours):9.1f}x" if warp_t else f"{'-':>9} {'-':>10}"
        print(f"{n:>5} {nv:>8} {nf:>8} | {min(ours) * 1e3:8.1f}ms {min(sk) * 1e3:8.1f}ms {min(ours) / min(sk):6.2f} "
              f"{pair:9.2f} | {warp_s} | {peak:8.1f}")
        if (sv, sf) != (nv, nf):
            print(f"      note: skimage gave V={sv}, F={sf} (Lewiner resolves ambiguous cells differently)")


if __name__ == "__main__":
    main()
