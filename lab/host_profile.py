# SPDX-License-Identifier: Apache-2.0
"""Where a fit iteration's host time goes: cProfile over a short CPU fit of the built-in bunny at tiny images
(kernels cost little there, so Python's share stands out). Prints the functions by own time and by calls,
per iteration.

    .venv/bin/python lab/host_profile.py [--iters 300 300] [--scale 0.25] [--top 40] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats

import wtopo
import wtopo.scenes
from wtopo.cli import _apply_set
from wtopo.fitting import FitConfig


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--iters", type=int, nargs=2, default=(300, 300))
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    scene = wtopo.scenes.load("bunny")
    cfg = FitConfig()
    for item in ["runtime.device=cpu", "runtime.usd_every=0", f"runtime.image_scale={a.scale}",
                 f"warmup.iterations={a.iters[0]}", f"coevolution.iterations={a.iters[1]}", *a.set]:
        _apply_set(cfg, item)
    pr = cProfile.Profile()
    pr.enable()
    wtopo.fit(scene, cfg, progress=False)
    pr.disable()
    n = sum(a.iters)
    st = pstats.Stats(pr)
    total_calls = sum(v[1] for v in st.stats.values())
    print(f"{total_calls / n:.0f} Python calls per iteration ({n} iterations)")
    groups = {"warp's Python": "warp/_src/", "wtopo": "/wtopo/", "torch's Python": "torch/"}
    for label, key in groups.items():
        own = sum(v[2] for (f, _, _), v in st.stats.items() if key in f)
        calls = sum(v[1] for (f, _, _), v in st.stats.items() if key in f)
        print(f"{label}: {1e3 * own / n:.2f} ms own time and {calls / n:.0f} calls per iteration")
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[: a.top]
    print(f"{'own ms/it':>9} {'cum ms/it':>9} {'calls/it':>8}  function")
    for (f, line, name), (_cc, nc, tt, ct, _) in rows:
        print(f"{1e3 * tt / n:9.3f} {1e3 * ct / n:9.3f} {nc / n:8.1f}  {f.split('site-packages/')[-1]}:{line} {name}")
    print("-- by cumulative time")
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][3])[: a.top]
    for (f, line, name), (_cc, nc, tt, ct, _) in rows:
        print(f"{1e3 * tt / n:9.3f} {1e3 * ct / n:9.3f} {nc / n:8.1f}  {f.split('site-packages/')[-1]}:{line} {name}")


if __name__ == "__main__":
    main()
