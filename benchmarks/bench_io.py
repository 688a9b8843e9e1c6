# SPDX-License-Identifier: Apache-2.0
"""USD timeline size and write time per 100 samples (wtopo.io.TimelineWriter).

The peer is the raw float32 payload of the same samples (what a naive dump of every array at every
sample costs), measured in the same process; the ratio shows what skipping unchanged samples and
usdc encoding buy or cost.

Command: ``.venv/bin/python benchmarks/bench_io.py``
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np
import trimesh

from wtopo.io import TimelineWriter


def _mesh(k: int, subdiv: int):
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return m.vertices * (1 + 0.01 * k), m.faces


def run(samples: int, surfels: int, sh_k: int, mesh_every: int, splats: bool, subdiv: int) -> tuple[float, ...]:
    rng = np.random.default_rng(0)
    raw = 0
    with tempfile.TemporaryDirectory() as d:
        w = TimelineWriter(os.path.join(d, "t.usdc"), splats=splats, splat_sh_degree=None, max_surfels=10**9)
        t0 = time.perf_counter()
        for i in range(samples):
            n = surfels + 10 * i  # densification: the count changes every sample
            kw = dict(means=rng.normal(size=(n, 3)), quats=rng.normal(size=(n, 4)), scales=rng.uniform(0, 0.1, (n, 2)),
                      opacities=rng.uniform(0, 1, n), colors_or_sh=rng.normal(size=(n, sh_k, 3)))
            raw += n * (3 + 4 + 2 + 1 + 3 * sh_k + 3) * 4
            if i % mesh_every == 0:
                v, f = _mesh(i, subdiv + (i // mesh_every) % 2)  # topology alternates at every mesh change
                kw.update(mesh_verts=v, mesh_faces=f)
                raw += (v.size * 2 + f.size) * 4
            w.add_sample(i * 10, **kw)
        t1 = time.perf_counter()
        stats = w.close()
        t2 = time.perf_counter()
    return stats.bytes_per_100_samples, 100 * raw / samples, (t1 - t0) / samples, (t2 - t1)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--samples", type=int, default=20)
    p.add_argument("--surfels", type=int, default=20_000)
    a = p.parse_args()
    print(f"{a.samples} samples, {a.surfels} surfels (+10 per sample), icosphere proxy mesh (subdivisions 4/5)")
    size, raw, _, _ = run(a.samples, 0, 1, 1, False, 4)
    print(f"mesh only, changing every sample: {size / 1e6:.2f} MB/100 samples (raw {raw / 1e6:.2f})")
    print(f"{'case':44s} {'MB/100 samples':>15s} {'raw MB/100':>11s} {'ratio':>6s} {'add_sample ms':>14s} "
          f"{'close s':>8s}")
    for sh_k, mesh_every, splats in [(1, 1, False), (1, 5, False), (1, 1, True), (16, 1, True)]:
        size, raw, t_add, t_close = run(a.samples, a.surfels, sh_k, mesh_every, splats, 4)
        name = f"SH K={sh_k:2d}, mesh every {mesh_every} sample(s), splats={'on' if splats else 'off'}"
        print(f"{name:44s} {size / 1e6:15.2f} {raw / 1e6:11.2f} {size / raw:6.2f} {1e3 * t_add:14.1f} {t_close:8.2f}")


if __name__ == "__main__":
    main()
