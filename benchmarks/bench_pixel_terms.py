# SPDX-License-Identifier: Apache-2.0
"""Benchmark of the fused normal, distortion and mask terms (:func:`wtopo.pixel_terms.pixel_terms`) against the
torch formulation they replaced (``tests/reference/pixel_terms.py``: depth normals, then each term as torch
operations), in the same process, on rough synthetic maps (a bumpy depth with a step, random opacities, normals,
distortion and mask). Before timing it checks that the two agree (values and gradients) on that device.

Times are milliseconds per view, the best of ``--repeats`` passes of ``--iters`` calls, synchronised around each
pass on CUDA (the kernels included), forward and forward + backward. Command (writes nothing; the figures go to
benchmarks/losses.md and benchmarks/gpu.md by hand)::

    .venv/bin/python benchmarks/bench_pixel_terms.py                       # 128 x 128 on the CPU
    python benchmarks/bench_pixel_terms.py --device cuda --size 800 600     # #60's 800 x 600
"""

from __future__ import annotations

import argparse
import time

import torch
from _from_tests import load  # beside this script

from wtopo.pixel_terms import pixel_terms


def _maps(w: int, h: int, device: str, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    j, i = torch.meshgrid(torch.arange(w) + 0.5, torch.arange(h) + 0.5, indexing="xy")
    d = torch.stack([(j - w / 2) / (0.8 * w), (i - h / 2) / (0.8 * w), torch.ones_like(j)], -1)
    o = torch.tensor([0.1, -0.2, 0.3]).expand(h, w, 3).contiguous()
    depth = 2.0 + 0.05 * torch.rand(h, w, generator=g)
    depth[:, w // 2:] += 1.0
    alpha = 0.02 + 0.96 * torch.rand(h, w, generator=g)
    normal = torch.randn(h, w, 3, generator=g) * alpha[..., None]
    dist = 1e-3 * torch.rand(h, w, generator=g)
    target = torch.rand(h, w, generator=g) > 0.5
    normal, alpha, depth, dist, o, d, target = (t.to(device) for t in (normal, alpha, depth, dist, o, d, target))
    for t in (normal, alpha, dist):
        t.requires_grad_()
    return normal, alpha, depth, dist, o, d, alpha.detach() >= 0.5, target


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, nargs=2, default=(128, 128), metavar=("W", "H"))
    ap.add_argument("--iters", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    ref = load("reference/pixel_terms.py").pixel_terms_torch
    args = _maps(*a.size, a.device)
    wts = (0.05, 100.0, 0.7)

    def loss(fn):
        return sum(w * t for w, t in zip(wts, fn(*args)))

    ours, theirs = loss(pixel_terms), loss(ref)
    g1 = torch.autograd.grad(ours, (args[0], args[1], args[3]))
    g2 = torch.autograd.grad(theirs, (args[0], args[1], args[3]))
    dv = abs(float(ours.detach()) - float(theirs.detach())) / abs(float(theirs.detach()))
    dg = max(float((x - y).abs().max()) / max(float(y.abs().max()), 1e-30) for x, y in zip(g1, g2))
    print(f"{a.size[0]}x{a.size[1]} on {a.device}: loss relative difference {dv:.1e}, largest gradient "
          f"difference {dg:.1e} of the largest entry")

    def timed(fn, backward: bool) -> float:
        for _ in range(5):
            x = loss(fn)
            if backward:
                x.backward()
        best = float("inf")
        for _ in range(a.repeats):
            _sync(a.device)
            t = time.perf_counter()
            for _ in range(a.iters):
                x = loss(fn)
                if backward:
                    x.backward()
            _sync(a.device)
            best = min(best, (time.perf_counter() - t) / a.iters)
        return 1000 * best

    rows = {name: (timed(fn, False), timed(fn, True)) for name, fn in (("fused", pixel_terms), ("torch", ref))}
    print(f"  {'':8s} {'forward':>8s} {'fwd+bwd':>8s}  ms per view")
    for name, (f, b) in rows.items():
        print(f"  {name:8s} {f:8.3f} {b:8.3f}")
    (f1, b1), (f2, b2) = rows["fused"], rows["torch"]
    print(f"  fused / torch: forward {f1 / f2:.2f}x, forward + backward {b1 / b2:.2f}x")


if __name__ == "__main__":
    main()
