# SPDX-License-Identifier: Apache-2.0
"""Where a CUDA fit's iteration goes (#60's loop): DTU at the CUDA default from an exchange folder, with windows of
iterations measured four ways: plain wall time (synchronised at the window's ends), torch.profiler (every kernel's
device time, the device's busy time as the union of kernel intervals, kernels per iteration), and cProfile (Python's
own time per function). The fit stops after the last window.

    python3 lab/device/t_loop.py EXCH [--out DIR] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "benchmarks", "peers"))
from exchange import load  # noqa: E402

WINDOWS = [("plain", 900, 1000, "warm-up"), ("torch", 1000, 1040, "warm-up"), ("cprofile", 1100, 1300, "warm-up"),
           ("plain", 3400, 3500, "co-evolution"), ("torch", 3500, 3540, "co-evolution"),
           ("cprofile", 3600, 3800, "co-evolution")]


def _busy(events) -> tuple[float, float, int]:
    """(sum of kernel times, union of kernel intervals, kernel count) in ms over device events."""
    iv = sorted((e.time_range.start, e.time_range.end) for e in events)
    total = sum(b - a for a, b in iv)
    union, cur_a, cur_b = 0.0, None, None
    for a, b in iv:
        if cur_b is None or a > cur_b:
            if cur_b is not None:
                union += cur_b - cur_a
            cur_a, cur_b = a, b
        else:
            cur_b = max(cur_b, b)
    if cur_b is not None:
        union += cur_b - cur_a
    return total / 1e3, union / 1e3, len(iv)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("exchange")
    ap.add_argument("--out", default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--top", type=int, default=45)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--quick", action="store_true", help="windows at iterations 10-40 (a check of the script)")
    ap.add_argument("--full", action="store_true", help="run the fit to its end (final mesh, evaluation)")
    a = ap.parse_args()
    global WINDOWS
    if a.quick:
        WINDOWS = [("plain", 10, 20, "warm-up"), ("torch", 20, 25, "warm-up"), ("cprofile", 25, 40, "warm-up")]

    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting import loop as L
    from wtopo.fitting.config import FitConfig

    cfg = FitConfig()
    stop = max(w[2] for w in WINDOWS) + 1
    extra = [] if a.full else [f"runtime.stop_at={stop}", "runtime.usd_every=0"]
    for item in [*a.set, f"runtime.device={a.device}", *extra]:
        _apply_set(cfg, item)
    scene = load(a.exchange).scene()
    results: dict = {}
    state: dict = {}
    orig = L.FitRun._step

    def step(self, stage):
        it = self.it
        for kind, lo, hi, label in WINDOWS:
            key = f"{kind} {label} {lo}-{hi}"
            if it == lo:
                if torch.cuda.is_available():
                    torch.cuda.synchronize()
                state[key] = {"t": time.perf_counter()}
                if kind == "torch":
                    p = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])
                    p.__enter__()
                    state[key]["p"] = p
                elif kind == "cprofile":
                    c = cProfile.Profile()
                    c.enable()
                    state[key]["c"] = c
            if it == hi and key in state:
                if torch.cuda.is_available():
                    torch.cuda.synchronize()
                st = state.pop(key)
                n = hi - lo
                wall = (time.perf_counter() - st["t"]) * 1e3 / n
                r = {"wall_ms_per_it": wall}
                if "p" in st:
                    st["p"].__exit__(None, None, None)
                    prof = st["p"]
                    dev = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
                    tot, union, count = _busy(dev)
                    r.update(kernel_ms_per_it=tot / n, busy_ms_per_it=union / n, kernels_per_it=count / n)
                    r["table"] = prof.key_averages().table(sort_by="self_device_time_total", row_limit=a.top,
                                                           max_name_column_width=70)
                    r["cpu_table"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30,
                                                               max_name_column_width=70)
                if "c" in st:
                    st["c"].disable()
                    s = io.StringIO()
                    ps = pstats.Stats(st["c"], stream=s)
                    stats = ps.stats
                    calls = sum(v[1] for v in stats.values())
                    groups = {"warp": "warp/", "wtopo": "/wtopo/", "torch": "torch/"}
                    r["calls_per_it"] = calls / n
                    r["groups"] = {g: (1e3 * sum(v[2] for (f, _, _), v in stats.items() if k in f) / n,
                                       sum(v[1] for (f, _, _), v in stats.items() if k in f) / n)
                                   for g, k in groups.items()}
                    rows = sorted(stats.items(), key=lambda kv: -kv[1][2])[: a.top]
                    r["own"] = [f"{1e3 * tt / n:8.3f} {1e3 * ct / n:8.3f} {nc / n:7.1f}  "
                                f"{f.split('site-packages/')[-1]}:{line} {name}"
                                for (f, line, name), (_cc, nc, tt, ct, _) in rows]
                    rows = sorted(stats.items(), key=lambda kv: -kv[1][3])[: a.top]
                    r["cum"] = [f"{1e3 * tt / n:8.3f} {1e3 * ct / n:8.3f} {nc / n:7.1f}  "
                                f"{f.split('site-packages/')[-1]}:{line} {name}"
                                for (f, line, name), (_cc, nc, tt, ct, _) in rows]
                results[key] = r
                print(f"== {key}: {json.dumps({k: v for k, v in r.items() if not isinstance(v, (str, list))})}",
                      flush=True)
        return orig(self, stage)

    L.FitRun._step = step
    t0 = time.perf_counter()
    res = wtopo.fit(scene, cfg, out_dir=a.out, progress=False)
    print(f"fit {time.perf_counter() - t0:.1f} s, {res.report.get('iterations')} iterations, psnr "
          f"{res.report.get('psnr')}, status {res.report.get('status')}")
    for key, r in results.items():
        print(f"\n==== {key}")
        print(json.dumps({k: v for k, v in r.items() if not isinstance(v, (str, list))}))
        if "table" in r:
            print(r["table"])
            print(r["cpu_table"])
        if "own" in r:
            print("own ms/it, cum ms/it, calls/it")
            print("\n".join(r["own"]))
            print("-- by cumulative")
            print("\n".join(r["cum"]))


if __name__ == "__main__":
    main()
