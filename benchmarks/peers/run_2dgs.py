# SPDX-License-Identifier: Apache-2.0
"""The official 2DGS (``hbb1/2d-gaussian-splatting``) on an exchange folder (the peers benchmark).

Runs the checkout's own ``train.py`` and ``render.py`` with its DTU recipe (``--depth_ratio 1.0
--lambda_dist 1000``, 30,000 iterations; mesh: ``--num_cluster 1 --voxel_size 0.004 --sdf_trunc 0.016
--depth_trunc 3.0``, the post-processed ``fuse_post.ply``) on the exchange folder's COLMAP model at its
full resolution, then renders the held-out views with the checkout's renderer (``_peer_views.py``).
On a masked capture its source folder's images carry the masks as their alpha channel, the form 2DGS
reads masks in (its loader keeps an RGBA image's alpha as the view's mask): training still sees the
photographs' colours alone, and its TSDF fusion leaves the depth outside the masks out
(``utils/mesh_utils.py``, ``extract_mesh_bounded(mask_backgrond=True)``); without them it fuses whatever
depth its splats give the empty background too. The checkout's CUDA extensions
(``diff_surfel_rasterization``, ``simple_knn``) must be importable.

    python benchmarks/peers/run_2dgs.py EXCH OUT --checkout PATH [--iterations 30000]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _result import read_json, write_result  # noqa: E402
from exchange import load  # noqa: E402


def _run(cmd: list[str], cwd: str, log) -> None:
    log.write("$ " + " ".join(cmd) + "\n")
    log.flush()
    subprocess.run(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT, check=True)


def source_folder(exchange: str, dst: str) -> str:
    """2DGS's source folder for the exchange folder's COLMAP model: the model itself for a capture without
    masks; for a masked one a copy under ``dst`` whose training images are RGBA, the mask as alpha (the
    colours byte for byte the exchange's)."""
    from PIL import Image

    ex = load(exchange)
    col = os.path.abspath(os.path.join(exchange, "colmap"))
    if not ex.masked:
        return col
    os.makedirs(os.path.join(dst, "sparse", "0"), exist_ok=True)
    os.makedirs(os.path.join(dst, "images"), exist_ok=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):  # copies: 2DGS writes points3D.ply beside them
        shutil.copyfile(os.path.join(col, "sparse", "0", name), os.path.join(dst, "sparse", "0", name))
    for name in sorted(os.listdir(os.path.join(col, "images"))):
        rgb = Image.open(os.path.join(col, "images", name)).convert("RGB")
        mask = Image.open(os.path.join(exchange, "masks", name)).convert("L")
        rgb.putalpha(mask)
        rgb.save(os.path.join(dst, "images", name))
    return os.path.abspath(dst)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exchange")
    ap.add_argument("out")
    ap.add_argument("--checkout", required=True, help="path of a 2d-gaussian-splatting checkout")
    ap.add_argument("--iterations", type=int, default=30_000)
    ap.add_argument("--port", type=int, default=None, help="2DGS's viewer port (default: one per output folder)")
    ap.add_argument("--mesh-only", type=int, default=None, metavar="ITERATION",
                    help="skip training: mesh and render the checkpoint of this iteration of an earlier run")
    a = ap.parse_args(argv)

    import trimesh

    ex = load(a.exchange)  # fails before any training on a folder that is not an exchange folder
    src = source_folder(a.exchange, os.path.join(a.out, "source"))
    model = os.path.abspath(os.path.join(a.out, "model"))
    it = a.mesh_only or a.iterations
    if a.mesh_only is None:
        shutil.rmtree(model, ignore_errors=True)
    os.makedirs(a.out, exist_ok=True)
    port = a.port or 6009 + zlib.crc32(os.path.abspath(a.out).encode()) % 20000
    py = sys.executable
    peak = os.path.join(a.out, "peak_train.json")
    with open(os.path.join(a.out, "log.txt"), "a") as log:
        t0 = time.perf_counter()
        if a.mesh_only is None:
            _run([py, os.path.join(HERE, "_peak.py"), peak, "train.py", "-s", src, "-m", model, "--quiet",
                  "--test_iterations", "-1", "--depth_ratio", "1.0", "-r", "1", "--lambda_dist", "1000",
                  "--iterations", str(a.iterations), "--port", str(port),
                  "--save_iterations", *sorted({str(min(k, a.iterations)) for k in (7000, 15000, a.iterations)},
                                               key=int)], a.checkout, log)
        t_train = time.perf_counter() - t0
        _run([py, "render.py", "-s", src, "-m", model, "--quiet", "--skip_train", "--skip_test", "--iteration",
              str(it), "--depth_ratio", "1.0", "--num_cluster", "1", "--voxel_size", "0.004",
              "--sdf_trunc", "0.016", "--depth_trunc", "3.0"], a.checkout, log)
        wall = time.perf_counter() - t0
        views = os.path.join(a.out, "views.npz")
        _run([py, os.path.join(HERE, "_peer_views.py"), "2dgs", model, str(it), os.path.abspath(a.exchange), views],
             a.checkout, log)
    mesh = trimesh.load(os.path.join(model, "train", f"ours_{it}", "fuse_post.ply"), process=False)
    # the TSDF mesh before its largest-piece step (--num_cluster 1): how much of the surface that step dropped
    raw = os.path.join(model, "train", f"ours_{it}", "fuse.ply")
    raw_faces = len(trimesh.load(raw, process=False).faces) if os.path.exists(raw) else None
    v = np.load(views)
    if a.mesh_only is not None:
        wall = t_train = None  # an earlier run's training time is not known here
    run = {"wall_s": wall, "train_s": t_train, "iterations": it, "surfels": int(v["n"]),
           "tsdf_faces_before_largest_piece": raw_faces,
           # the training process's peak; unknown when only an earlier run's checkpoint was meshed
           "peak_gpu_bytes": (max(int(v["peak"]), read_json(peak)["peak_gpu_bytes"])
                              if a.mesh_only is None and os.path.exists(peak) else None),
           "recipe": "2DGS DTU: --depth_ratio 1.0 --lambda_dist 1000; TSDF 0.004/0.016/3.0, 1 cluster"
                     + ("; masks as the images' alpha (the TSDF fuses no depth outside them)" if ex.masked else "")}
    system = "2DGS" if it == 30_000 else f"2DGS ({it:,} it.)"
    write_result(a.out, system=system, mesh=mesh, renders=v["rgb"].astype(np.float32), run=run)


if __name__ == "__main__":
    main()
