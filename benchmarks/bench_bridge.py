# SPDX-License-Identifier: Apache-2.0
"""Host cost of one crossing of the torch <-> Warp bridge (``wtopo._bridge.apply``), against torch in the same process.

#60's loss goal (every per-pixel term in 1 ms an iteration) failed on the GPU with the terms fused behind the bridge
(``design/decisions.md``): the bridge's own host time per op exceeded the torch operations it replaced. This script
measures that time and where it goes, on two ops:

* ``tiny``: one bridged Warp kernel ``y = 2 x`` on 1,024 floats, against the torch op ``2 * x``: all host time;
* ``photometric``: the fused L1 + D-SSIM term (:func:`wtopo.photometric.photometric_loss`) on an image of
  ``--resolution`` px square, against its torch formulation (L1 + :func:`wtopo.metrics.ssim`).

For each it prints the milliseconds per call (and the ratio bridged / torch) of the forward and of forward +
backward, timed two ways: ``sync`` (every call waits for the device: what an iteration pays when the host is the
bottleneck and the device the rest) and ``host`` (``--calls`` calls queued without waiting, then one wait: the host's
time per call when the device keeps up). ``--profile`` adds Python's profile of the bridged forward + backward (the
functions with the most own time); ``--trace`` adds torch's profiler table of the same calls (host and device time
per operation and kernel, Warp's kernels included on CUDA).

``--against FILE`` adds a column for another version of the bridge module in the same process (its ``apply`` stands in
for the package's; e.g. ``git show REV:wtopo/_bridge.py > /tmp/bridge_rev.py``).

Commands (the figures go to benchmarks/gpu.md by hand)::

    .venv/bin/python benchmarks/bench_bridge.py                          # CPU
    python benchmarks/bench_bridge.py --device cuda --resolution 700 --profile
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import pstats
import time

import torch
import warp as wp
from _from_tests import load_file  # beside this script

from wtopo import _bridge
from wtopo.metrics import ssim
from wtopo.photometric import photometric_loss


@wp.kernel
def _double(x: wp.array(dtype=float), y: wp.array(dtype=float)):
    i = wp.tid()
    y[i] = 2.0 * x[i]


def _tiny_bridged(x: torch.Tensor) -> torch.Tensor:
    def run(xa):
        y = wp.empty(xa.shape, dtype=float, device=xa.device, requires_grad=True)
        _bridge.launch(_double, dim=xa.shape[0], inputs=[xa], outputs=[y], device=xa.device)
        return (y,)

    op = _bridge.WarpOp("double", run, in_dtypes=(None,), differentiable_inputs=(True,),
                        differentiable_outputs=(True,))
    return _bridge.apply(op, x)[0]


def _photo_torch(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return 0.8 * (pred - target).abs().mean() + 0.2 * (1.0 - ssim(pred, target))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _per_call(fn, device, calls: int, sync_each: bool, repeats: int = 3) -> float:
    """Best-of-``repeats`` milliseconds per call of ``fn`` over ``calls`` calls."""
    best = float("inf")
    for _ in range(repeats):
        _sync(device)
        t = time.perf_counter()
        for _ in range(calls):
            fn()
            if sync_each:
                _sync(device)
        _sync(device)
        best = min(best, (time.perf_counter() - t) / calls)
    return 1e3 * best


@contextlib.contextmanager
def _bridge_from(path: str | None):
    """Within: ``wtopo._bridge.apply`` is the one of the bridge module at ``path`` (``None``: the package's)."""
    if path is None:
        yield
        return
    other = load_file(path, "wtopo._bridge_against")  # in the package: its relative imports resolve
    kept = _bridge.apply
    _bridge.apply = other.apply
    try:
        yield
    finally:
        _bridge.apply = kept


def _cases(device: torch.device, resolution: int):
    gen = torch.Generator(device="cpu").manual_seed(0)
    x = torch.rand(1024, generator=gen).to(device).requires_grad_(True)
    img = torch.rand(resolution, resolution, 3, generator=gen).to(device)
    pred = (img + 0.05 * torch.rand(img.shape, generator=gen).to(device)).clamp(0, 1).requires_grad_(True)
    return {
        "tiny": (lambda: _tiny_bridged(x).sum(), lambda: (2.0 * x).sum(), x),
        "photometric": (lambda: photometric_loss(pred, img), lambda: _photo_torch(pred, img), pred),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--resolution", type=int, default=128, help="the photometric case's image side [px]")
    ap.add_argument("--calls", type=int, default=200, help="calls per timing")
    ap.add_argument("--profile", action="store_true", help="Python's profile of the bridged forward + backward")
    ap.add_argument("--trace", action="store_true", help="torch's profiler table of the bridged forward + backward")
    ap.add_argument("--against", default=None, help="another bridge module's file, timed beside the package's")
    args = ap.parse_args()
    device = torch.device(args.device)
    cases = _cases(device, args.resolution)
    print(f"device {device}, photometric at {args.resolution} x {args.resolution} px; ms per call, best of 3")
    versions = [None] + ([args.against] if args.against else [])
    cols = ["bridged"] + (["against"] if args.against else []) + ["torch"]
    print(f"{'op':12s} {'pass':8s} {'timing':6s} " + " ".join(f"{c:>9s}" for c in cols) + f" {'ratio':>7s}")
    for name, (bridged, reference, leaf) in cases.items():
        def fwd_bwd(f=None, leaf=leaf):
            f().backward()
            leaf.grad = None

        for version in versions:  # compile, allocate, warm the caches
            with _bridge_from(version):
                for f in (bridged, reference):
                    for _ in range(3):
                        fwd_bwd(f)
        for pass_name in ("fwd", "fwd+bwd"):
            for timing in ("sync", "host"):
                ms = []
                for version, f in [(v, bridged) for v in versions] + [(None, reference)]:
                    call = f if pass_name == "fwd" else (lambda f=f: fwd_bwd(f))
                    with _bridge_from(version), torch.no_grad() if pass_name == "fwd" else torch.enable_grad():
                        ms.append(_per_call(call, device, args.calls, timing == "sync"))
                print(f"{name:12s} {pass_name:8s} {timing:6s} " + " ".join(f"{m:9.3f}" for m in ms)
                      + f" {ms[0] / ms[-1]:7.2f}")
    if args.profile:
        for name, (bridged, _, leaf) in cases.items():
            prof = cProfile.Profile()
            _sync(device)
            prof.enable()
            for _ in range(args.calls):
                bridged().backward()
                leaf.grad = None
            _sync(device)
            prof.disable()
            out = io.StringIO()
            pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(22)
            print(f"\n== profile of {args.calls} bridged forward + backward calls: {name}")
            print("\n".join(line for line in out.getvalue().splitlines()[5:] if line.strip()))
    if args.trace:
        acts = [torch.profiler.ProfilerActivity.CPU]
        if device.type == "cuda":
            acts.append(torch.profiler.ProfilerActivity.CUDA)
        for name, (bridged, _, leaf) in cases.items():
            _sync(device)
            with torch.profiler.profile(activities=acts) as prof:
                for _ in range(args.calls):
                    bridged().backward()
                    leaf.grad = None
                _sync(device)
            key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
            print(f"\n== torch profiler, {args.calls} bridged forward + backward calls: {name}")
            print(prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=48))


if __name__ == "__main__":
    main()
