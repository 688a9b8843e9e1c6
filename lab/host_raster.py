# SPDX-License-Identifier: Apache-2.0
"""Host time of the fit's rasterizer path (``_rasterize_trusted``, deferred count) on a tiny scene, where the kernels
cost next to nothing: the Python, dispatch and launch overhead that bounds a CUDA fit's forward at 100k surfels.
Prints ms per forward and per backward, then cProfile's own time per function.

    WTOPO_NUM_THREADS=1 .venv/bin/python lab/host_raster.py [--device cpu] [--n 200] [--px 32] [--calls 300] [--graph]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import torch

import wtopo
import wtopo.rasterize as R


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--px", type=int, default=32)
    ap.add_argument("--calls", type=int, default=300)
    ap.add_argument("--top", type=int, default=35)
    ap.add_argument("--graph", action="store_true", help="the fit's replayed render (wtopo.fitting.raster_graph; on "
                    "the CPU with the capture emulated) of the same surfels")
    a = ap.parse_args()
    dev = torch.device(a.device)
    g = torch.Generator().manual_seed(0)
    n = a.n
    means = (torch.rand(n, 3, generator=g) * 2 - 1).to(dev).requires_grad_()
    quats = torch.randn(n, 4, generator=g).to(dev).requires_grad_()
    scales = (torch.rand(n, 2, generator=g) * 0.1 + 0.02).to(dev).requires_grad_()
    opac = (torch.rand(n, generator=g) * 0.8 + 0.1).to(dev).requires_grad_()
    sh = (torch.randn(n, 16, 3, generator=g) * 0.2).to(dev).requires_grad_()
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.7, width=a.px, height=a.px)
    bg = torch.zeros(3, device=dev)
    cfg = R.RasterConfig()
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    graphs = None
    if a.graph:
        from wtopo.fitting.raster_graph import RasterGraphs
        from wtopo.fitting.surfels import Surfels

        s = Surfels(means=means, quats=quats, log_scales=scales.log(), opacity_logits=torch.logit(opac),
                    sh_dc=sh[:, :1], sh_rest=sh[:, 1:])
        graphs = RasterGraphs(bg, cfg, make=None if dev.type == "cuda" else (lambda fn, samples, **kw: fn))
        R._rasterize_trusted(s.means, s.quats, s.scales, s.opacities, s.sh, cam, sh_degree=3, background=bg,
                             config=cfg, defer_count=False)  # measures the pair capacity

    def fwd():
        if graphs is not None:
            out = graphs(s, cam)
            assert out is not None, graphs.failure
        else:
            out = R._rasterize_trusted(means, quats, scales, opac, sh, cam, sh_degree=3, background=bg, config=cfg,
                                       defer_count=True)
        return (out.rgb.sum() + out.alpha.sum() + out.depth.sum() + out.median_depth.sum() + out.normal.sum()
                + out.distortion.sum())

    for _ in range(20):
        fwd().backward()
    sync()
    tf = tb = 0.0
    for _ in range(a.calls):
        t0 = time.perf_counter()
        loss = fwd()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        tf += t1 - t0
        tb += t2 - t1
    sync()
    print(f"host: forward {1e3 * tf / a.calls:.3f} ms, backward {1e3 * tb / a.calls:.3f} ms (n={n}, {a.px} px, "
          f"{a.device})")
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(a.calls):
        fwd().backward()
    pr.disable()
    st = pstats.Stats(pr)
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[: a.top]
    print(f"{'own us':>8} {'cum us':>8} {'calls':>6}  function (per forward + backward)")
    for (f, line, name), (_cc, nc, tt, ct, _) in rows:
        print(f"{1e6 * tt / a.calls:8.1f} {1e6 * ct / a.calls:8.1f} {nc / a.calls:6.1f}  "
              f"{f.split('site-packages/')[-1].split('/work/main/')[-1]}:{line} {name}")


if __name__ == "__main__":
    main()
