# SPDX-License-Identifier: Apache-2.0
"""Lab (nothing imports it): what writing the USD timeline costs a loop that is bound by its host's Python, with
the writer on a thread of the fit's process (the fit until 2026-12-05) and in a writer process
(:class:`wtopo.io._timeline_process.TimelineProcess`, today's). The loop spends ``--ms`` of pure Python an
iteration and hands over a DTU-sized sample every ``--every`` iterations (52k surfels, a 327k-face mesh moved a
little at each sample); printed: the loop's wall with no timeline, with each writer, and the close.

    .venv/bin/python lab/timeline_gil.py [--iterations 2000] [--every 100] [--ms 5]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import trimesh

from wtopo.io import TimelineWriter
from wtopo.io._timeline_process import TimelineProcess


def busy(count: int) -> None:
    """A fixed amount of pure Python (not a fixed wall time: a loop that waits for the GIL or a core takes longer)."""
    x = 0
    for k in range(count):
        x ^= k


def calibrate(ms: float) -> int:
    """The ``busy`` count that takes ``ms`` on this host, alone."""
    count = 100_000
    t0 = time.perf_counter()
    busy(count)
    return max(1, int(count * ms / 1e3 / (time.perf_counter() - t0)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--ms", type=float, default=5.0)
    a = ap.parse_args()
    g = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=7)  # 327,680 faces
    n = 52_000
    surf = {"means": g.random((n, 3)), "quats": g.standard_normal((n, 4)).astype(np.float32),
            "scales": g.random((n, 2)) * 0.01, "opacities": g.random(n).astype(np.float32),
            "colors_or_sh": g.random((n, 1, 3)).astype(np.float32)}

    def sample(k):
        return dict(surf, means=surf["means"] + 1e-3 * k, mesh_verts=mesh.vertices * (1 + 1e-3 * k),
                    mesh_faces=mesh.faces)

    count = calibrate(a.ms)

    def loop(hand_over):
        t0 = time.perf_counter()
        for it in range(1, a.iterations + 1):
            busy(count)
            if it % a.every == 0:
                hand_over(it, sample(it))
        return time.perf_counter() - t0

    with tempfile.TemporaryDirectory() as d:
        base = loop(lambda it, s: None)
        print(f"no timeline: loop {base:.2f} s")

        w = TimelineWriter(Path(d) / "thread.usdc")
        pool = ThreadPoolExecutor(max_workers=1)
        pending = []

        def thread_hand_over(it, s):
            if pending:
                pending.pop().result()
            pending.append(pool.submit(w.add_sample, it, **s))

        t = loop(thread_hand_over)
        t0 = time.perf_counter()
        if pending:
            pending.pop().result()
        w.close()
        print(f"writer thread: loop {t:.2f} s (+{t - base:.2f}), close {time.perf_counter() - t0:.2f} s")

        p = TimelineProcess(Path(d) / "process.usdc")
        t = loop(lambda it, s: p.add_sample(it, **s))
        t0 = time.perf_counter()
        p.close()
        print(f"writer process: loop {t:.2f} s (+{t - base:.2f}), close {time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
