# SPDX-License-Identifier: Apache-2.0
"""Face orientation of a scrambled closed mesh: wtopo's orient_faces against trimesh's fix_normals.

The final mesh's repair orients its faces (``wtopo.fitting.tsdf.repair_mesh``). It used trimesh's
``fix_normals``, a breadth-first walk over the face adjacency in Python, which kept a 512-px ten-view
cup's fit on one core for over 15 minutes. The peer is that call, in
the same process, on the same icosphere with a share of its faces reversed; both results are checked
(consistent winding, the sphere's orientation back).

Command: ``.venv/bin/python benchmarks/bench_winding.py [--subdivisions 5 6 7] [--fraction 0.3]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from wtopo.geometry.winding import orient_faces


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subdivisions", type=int, nargs="+", default=[5, 6, 7])
    ap.add_argument("--fraction", type=float, default=0.3, help="share of the faces reversed")
    ap.add_argument("--peer-max-faces", type=int, default=400_000, help="skip trimesh above this many faces")
    args = ap.parse_args(argv)
    print("| faces | orient_faces s | trimesh fix_normals s | ratio | both back to the sphere |")
    print("|---|---|---|---|---|")
    for sd in args.subdivisions:
        s = trimesh.creation.icosphere(subdivisions=sd)
        rng = np.random.default_rng(sd)
        f = s.faces.copy()
        mask = rng.random(len(f)) < args.fraction
        f[mask] = f[mask][:, ::-1]
        t = time.perf_counter()
        ours = orient_faces(f)
        t_ours = time.perf_counter() - t
        ok = bool((ours == s.faces).all())
        t_peer = float("nan")
        if len(f) <= args.peer_max_faces:
            m = trimesh.Trimesh(s.vertices, f, process=False)
            t = time.perf_counter()
            trimesh.repair.fix_normals(m)
            t_peer = time.perf_counter() - t
            ok = ok and m.is_winding_consistent and m.volume > 0
        ratio = f"{t_peer / t_ours:.0f}x faster" if np.isfinite(t_peer) else "-"
        print(f"| {len(f):,} | {t_ours:.3f} | {t_peer:.2f} | {ratio} | {ok} |", flush=True)


if __name__ == "__main__":
    main()
