# SPDX-License-Identifier: Apache-2.0
"""Benchmark of the fit's Adam step (the ``optimizer`` section of the profile) against torch's Adams.

Builds the surfel parameters of a fit (means [N, 3], quaternions [N, 4], log scales [N, 2], opacity logits
[N, 1], SH DC [N, 1, 3] and the higher bands of degree 3 [N, 15, 3]), one group each with its own rate as the
fit's, and times one step with fresh gradients, synchronised, for:

* ``wtopo``: :class:`wtopo.fitting.adam.Adam` (torch's multi-tensor operations; non-finite gradients zeroed and
  flagged), replayed as a CUDA graph on CUDA; ``eager``: the same with :data:`wtopo.fitting.adam.GRAPHS` off;
* ``torch single-tensor``: ``torch.optim.Adam(foreach=False)``, the per-parameter update wtopo's class made
  before (the same operations, seven per parameter);
* ``torch foreach`` and, on CUDA, ``torch fused``: ``torch.optim.Adam(foreach=True)`` and ``(fused=True)``,
  the peers in the same process;
* ``foreach+checks``: the fit's optimizer section before the checks moved into the step: the checks around a
  multi-tensor step (the gradients' norms, ``nan_to_num_`` of each, ``torch.optim.Adam(foreach=True)``, the
  parameters' norms), where wtopo's step zeroes non-finite gradient elements and flags non-finite ones itself.

Besides the synchronised time, ``host`` columns give wtopo's and the eager step's own host time (the call alone,
from an idle device): what a fit bound by its host pays. Every optimiser updates its own copy of the parameters;
the script checks that wtopo's copy equals torch's single-tensor copy after the timed steps.

Commands (the figures go to benchmarks/gpu.md by hand)::

    .venv/bin/python benchmarks/bench_optimizer.py --device cpu --surfels 20000
    python benchmarks/bench_optimizer.py --device cuda --surfels 100000 1000000
"""

from __future__ import annotations

import argparse
import time

import torch

import wtopo.fitting.adam as adam_mod
from wtopo.fitting.adam import Adam

_SHAPES = {"means": (3,), "quats": (4,), "log_scales": (2,), "opacity_logits": (1,), "sh_dc": (1, 3),
           "sh_rest": (15, 3)}
_RATES = {"means": 1.6e-4, "quats": 1e-3, "log_scales": 5e-3, "opacity_logits": 5e-2, "sh_dc": 2.5e-3,
          "sh_rest": 1.25e-4}


def _params(n: int, device, seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator(device="cpu").manual_seed(seed)
    return [torch.randn((n, *s), generator=g).to(device).requires_grad_() for s in _SHAPES.values()]


def _groups(params):
    return [{"params": [p], "lr": _RATES[k], "name": k} for k, p in zip(_SHAPES, params)]


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _Checked:
    """A step with the finite checks the fit's optimizer section made around its multi-tensor step."""

    def __init__(self, opt, params):
        self.opt, self.params = opt, params

    def step(self):
        grads = [p.grad for p in self.params]
        finite = torch.isfinite(torch.stack(torch._foreach_norm(grads))).all()
        for g in grads:
            g.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
        self.opt.step()
        return torch.isfinite(torch.stack(torch._foreach_norm([p.detach() for p in self.params]))).all() & finite


class _Eager:
    """wtopo's step with its CUDA graph off."""

    def __init__(self, opt):
        self.opt = opt

    def step(self):
        adam_mod.GRAPHS = False
        try:
            return self.opt.step()
        finally:
            adam_mod.GRAPHS = True


def _time(opt, params, grads, steps: int, device) -> tuple[float, float]:
    """Median ms of ``steps`` synchronised steps (gradients assigned before each, not timed), and the median host
    time of the call alone."""
    times, host = [], []
    for k in range(steps):
        for p, g in zip(params, grads[k % len(grads)]):
            p.grad = g
        _sync(device)
        t = time.perf_counter()
        opt.step()
        host.append((time.perf_counter() - t) * 1e3)
        _sync(device)
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    host.sort()
    return times[len(times) // 2], host[len(host) // 2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--surfels", type=int, nargs="+", default=[100_000])
    ap.add_argument("--steps", type=int, default=200)
    args = ap.parse_args()
    device = torch.device(args.device)
    print(f"Adam step, {args.steps} synchronised steps each, median ms ({device}, torch {torch.__version__})")
    print(f"{'surfels':>9} {'wtopo':>8} {'eager':>8} {'single':>8} {'foreach':>8} {'fused':>8} {'f+checks':>8}"
          f"  wtopo / best torch  wtopo / f+checks  {'host wtopo':>10} {'host eager':>10} {'host fused':>10}")
    for n in args.surfels:
        grads = [[torch.randn((n, *s), device=device) for s in _SHAPES.values()] for _ in range(4)]
        runs = {"wtopo": lambda ps: Adam(_groups(ps), eps=1e-15),
                "eager": lambda ps: _Eager(Adam(_groups(ps), eps=1e-15)),
                "single": lambda ps: torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15, foreach=False),
                "foreach": lambda ps: torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15, foreach=True),
                "checked": lambda ps: _Checked(torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15, foreach=True), ps)}
        if device.type == "cuda":
            runs["fused"] = lambda ps: torch.optim.Adam(_groups(ps), lr=0.0, eps=1e-15, fused=True)
        ms, host, finals = {}, {}, {}
        for name, make in runs.items():
            ps = _params(n, device)
            opt = make(ps)
            _time(opt, ps, grads, 10, device)  # first steps allocate the moments
            ms[name], host[name] = _time(opt, ps, grads, args.steps, device)
            finals[name] = ps
        for other in ("single", "eager"):
            for a, b in zip(finals["wtopo"], finals[other]):
                torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
        best = min(v for k, v in ms.items() if k not in ("wtopo", "eager", "checked"))
        cells = " ".join(f"{ms.get(k, float('nan')):8.3f}" for k in ("wtopo", "eager", "single", "foreach", "fused",
                                                                      "checked"))
        hosts = " ".join(f"{host.get(k, float('nan')):10.3f}" for k in ("wtopo", "eager", "fused"))
        print(f"{n:9d} {cells}  {ms['wtopo'] / best:17.2f}x  {ms['wtopo'] / ms['checked']:15.2f}x  {hosts}")


if __name__ == "__main__":
    main()
