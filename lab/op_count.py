# SPDX-License-Identifier: Apache-2.0
"""Torch operations of one fit iteration, by the wtopo line that issued them (a TorchDispatchMode over one
warm-up and one co-evolution step of a small CPU fit): where the loop's host time per iteration is spent on
CUDA, where every torch operation costs several microseconds of Python and dispatch.

    .venv/bin/python lab/op_count.py [--scene bunny] [--at 40 70] [--only OP] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import collections
import sys
import traceback

from torch.utils._python_dispatch import TorchDispatchMode

import wtopo
import wtopo.scenes
from wtopo.cli import _apply_set
from wtopo.fitting import FitConfig
from wtopo.fitting import loop as L


class Count(TorchDispatchMode):
    def __init__(self, only: str | None = None):
        super().__init__()
        self.only = only
        self.ops = collections.Counter()
        self.sites = collections.Counter()
        self.backward_ops = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket.__name__)
        self.ops[name] += 1
        if self.only and name != self.only:
            return func(*args, **(kwargs or {}))
        site = "?"
        for fr in reversed(traceback.extract_stack(limit=40)[:-1]):
            if "/wtopo/" in fr.filename and "_python_dispatch" not in fr.filename:
                site = f"{fr.filename.split('/wtopo/')[-1]}:{fr.lineno} {fr.name}"
                break
        self.sites[site] += 1
        if site.startswith("fitting/loop.py") and "_step" in site:
            self.backward_ops[name] += 1
        return func(*args, **(kwargs or {}))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="bunny")
    ap.add_argument("--at", type=int, nargs="+", default=[40, 70])
    ap.add_argument("--top", type=int, default=60)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--only", default=None, help="sites of this op alone (e.g. detach)")
    a = ap.parse_args()
    scene = wtopo.scenes.load(a.scene)
    cfg = FitConfig()
    for item in ["runtime.device=cpu", "runtime.usd_every=0", "runtime.image_scale=0.25", "warmup.iterations=50",
                 "coevolution.iterations=30", f"runtime.stop_at={max(a.at) + 1}", *a.set]:
        _apply_set(cfg, item)
    orig = L.FitRun._step

    def step(self, stage):
        if self.it not in a.at:
            return orig(self, stage)
        with Count(a.only) as c:
            r = orig(self, stage)
        print(f"\n== iteration {self.it} ({stage.value}): {sum(c.ops.values())} torch ops")
        for site, k in c.sites.most_common(a.top):
            print(f"{k:5d}  {site}")
        bwd = ", ".join(f"{op} {k}" for op, k in c.backward_ops.most_common(40))
        print(f"-- in the backward (autograd engine): {bwd}")
        print("-- by op")
        print(", ".join(f"{op} {k}" for op, k in c.ops.most_common(40)))
        sys.stdout.flush()
        return r

    L.FitRun._step = step
    wtopo.fit(scene, cfg, progress=False)


if __name__ == "__main__":
    main()
