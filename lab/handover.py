# SPDX-License-Identifier: Apache-2.0
"""Lab (nothing imports it): what handing a DTU-sized timeline sample (52k surfels, a 327k-face mesh: 16 MB) to
another process costs on this host, by way: pickled to a file in the temporary folder, in /dev/shm, into a pipe
(a reader draining it), and the writer's own add_sample on this thread for comparison. ms per sample, median of 7.

    .venv/bin/python lab/handover.py
"""

from __future__ import annotations

import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import trimesh

from wtopo.io import TimelineWriter


def main() -> None:
    g = np.random.default_rng(0)
    mesh = trimesh.creation.icosphere(subdivisions=7)
    n = 52_000
    s = {"means": g.random((n, 3)), "quats": g.standard_normal((n, 4)).astype(np.float32),
         "scales": g.random((n, 2)) * 0.01, "opacities": g.random(n).astype(np.float32),
         "colors_or_sh": g.random((n, 1, 3)).astype(np.float32), "mesh_verts": np.array(mesh.vertices),
         "mesh_faces": np.array(mesh.faces)}

    def ms(fn, k=7):
        t = []
        for i in range(k):
            t0 = time.perf_counter()
            fn(i)
            t.append(1e3 * (time.perf_counter() - t0))
        return statistics.median(t)

    print(f"pickle.dumps alone: {ms(lambda i: pickle.dumps(s, protocol=5)):.1f} ms")
    for folder in (tempfile.gettempdir(), "/dev/shm"):
        if not os.path.isdir(folder):
            continue
        d = tempfile.mkdtemp(dir=folder)

        def to_file(i, d=d):
            with open(os.path.join(d, f"{i}"), "wb") as f:
                pickle.dump(s, f, protocol=5)

        print(f"to a file in {folder}: {ms(to_file):.1f} ms")
    reader = subprocess.Popen([sys.executable, "-c", "import sys\nwhile sys.stdin.buffer.read(1 << 20): pass"],
                              stdin=subprocess.PIPE)

    def to_pipe(i):
        pickle.dump(s, reader.stdin, protocol=5)
        reader.stdin.flush()

    print(f"into a pipe: {ms(to_pipe):.1f} ms")
    reader.stdin.close()
    reader.wait()
    w = TimelineWriter(os.path.join(tempfile.mkdtemp(), "t.usdc"))
    print(f"TimelineWriter.add_sample on this thread: "
          f"{ms(lambda i: w.add_sample(i, **dict(s, means=s['means'] + i))):.1f} ms")
    t0 = time.perf_counter()
    w.close()
    print(f"close: {1e3 * (time.perf_counter() - t0):.0f} ms")


if __name__ == "__main__":
    main()
