# SPDX-License-Identifier: Apache-2.0
"""Where a profiled fit's "outside any section" time goes: the host time between one top-level section's end and
the next one's start, summed per (previous section, next section) pair.

    .venv/bin/python lab/outside_gaps.py bunny --stop-at 300 [--device cuda]

SCENE: a built-in scene or a path the loaders read (an exported exchange folder). Runs ``wtopo.fit`` with
``runtime.profile=true`` and ``runtime.stop_at``, without progress bars unless ``--progress``, then prints the pairs
by total gap (ms) and calls, and the fit's own "outside any section" figure to compare.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import wtopo
from wtopo import scenes
from wtopo._profile import in_section
from wtopo.fitting import profiling
from wtopo.fitting.config_fields import set_field


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--stop-at", type=int, default=300)
    ap.add_argument("--device", default=None)
    ap.add_argument("--progress", action="store_true", help="show the progress bars (their refreshes count)")
    a = ap.parse_args()
    gaps: dict = defaultdict(lambda: [0.0, 0])
    last = {"name": "start", "t": None}
    orig = profiling.Timers.__call__

    @contextlib.contextmanager
    def timed(self, name):
        top = not in_section()
        if top and last["t"] is not None:
            row = gaps[(last["name"], name)]
            row[0] += time.perf_counter() - last["t"]
            row[1] += 1
        with orig(self, name):
            yield
        if top:
            last["name"], last["t"] = name, time.perf_counter()

    profiling.Timers.__call__ = timed
    cfg = wtopo.FitConfig()
    set_field(cfg, "runtime.stop_at", a.stop_at)
    set_field(cfg, "runtime.profile", True)
    if a.device:
        set_field(cfg, "runtime.device", a.device)
    with tempfile.TemporaryDirectory() as out:
        if os.path.exists(os.path.join(a.scene, "meta.json")):  # an exported exchange folder (benchmarks/peers)
            sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "peers"))
            from exchange import load

            scene = load(a.scene).scene()
        elif os.path.exists(a.scene):
            from wtopo.loaders import detect_format, load_scene

            scene = load_scene(a.scene, format=detect_format(a.scene))
        else:
            scene = scenes.load(a.scene)
        wtopo.fit(scene, cfg, out_dir=out, progress=a.progress)
        prof = json.loads((Path(out) / "report.json").read_text()).get("profile", {})
    total = sum(v[0] for v in gaps.values())
    print(f"gaps between top-level sections: {1e3 * total:.1f} ms; the fit's outside: "
          f"{1e3 * prof.get('outside_s', float('nan')):.1f} ms")
    for (p, n), (s, c) in sorted(gaps.items(), key=lambda kv: -kv[1][0])[:20]:
        print(f"{1e3 * s:9.1f} ms {c:6d} calls {1e3 * s / c:8.3f} ms/call  {p} -> {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
