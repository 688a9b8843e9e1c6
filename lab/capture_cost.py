# SPDX-License-Identifier: Apache-2.0
"""Lab (nothing imports it): what one recapture of the fit's render graph costs after a density step, by part.
Random surfels at a DTU-like count and view (800 x 600, SH degree 3); each round adds surfels (a density step),
then times, with the device synchronised around each part: the whole ``RasterGraphs`` capture (make_graphed +
its check), ``make_graphed`` alone, the same with ``torch.cuda.empty_cache`` a no-op during the capture (torch's
``graph.__enter__`` empties the allocator's cache at each of the forward's and the backward's capture), the
check alone, then the first ten iterations after the capture (the allocator refilling its cache) and ten
iterations later on. Adam's step graph for the same count likewise.

    python3 lab/capture_cost.py [--n 100000] [--rounds 4] [--grow 3000]
"""

from __future__ import annotations

import argparse
import time

import torch

import wtopo
import wtopo.rasterize as R
from wtopo import _graphs
from wtopo.fitting import raster_graph
from wtopo.fitting.surfels import Surfels
from wtopo.rasterize._graphable import check_replay


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--grow", type=int, default=3000)
    a = ap.parse_args()
    dev = torch.device("cuda", torch.cuda.current_device())
    g = torch.Generator().manual_seed(0)
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.7, width=800, height=600)
    bg = torch.zeros(3, device=dev)
    cfg = R.RasterConfig()
    sync = torch.cuda.synchronize

    def surfels(n):
        t = {"means": torch.rand(n, 3, generator=g) * 2 - 1, "quats": torch.randn(n, 4, generator=g),
             "log_scales": (torch.rand(n, 2, generator=g) * 0.02 + 0.005).log(),
             "opacity_logits": torch.randn(n, generator=g), "sh_dc": torch.randn(n, 1, 3, generator=g) * 0.2,
             "sh_rest": torch.randn(n, 15, 3, generator=g) * 0.05}
        return Surfels(**{k: v.to(dev).requires_grad_() for k, v in t.items()})

    def timed(fn):
        sync()
        t0 = time.perf_counter()
        r = fn()
        sync()
        return r, 1e3 * (time.perf_counter() - t0)

    def iterate(graphs, s, k):
        def run():
            for _ in range(k):
                out = graphs(s, cam)
                (out.rgb.sum() + out.depth.sum()).backward()
        return timed(run)[1] / k

    def one_round(n):
        s = surfels(n)
        R._rasterize_trusted(s.means, s.quats, s.scales, s.opacities, s.sh, cam, sh_degree=3, background=bg,
                             config=cfg, defer_count=False)
        graphs = raster_graph.RasterGraphs(bg, cfg)
        _, whole = timed(lambda: graphs(s, cam))
        first = iterate(graphs, s, 10)
        later = iterate(graphs, s, 10)
        capacity = R._binning._pair_capacity(wtopo._bridge.warp_device(dev)).value  # noqa: SLF001
        fn = raster_graph._function(raster_graph.Size(cam.width, cam.height), 3, bg, cfg,
                                    raster_graph.pair_budget(capacity, cfg.max_intersections))
        p = s.params
        shift = torch.zeros(n, 2, device=dev, requires_grad=True)
        args = (p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["sh_dc"], p["sh_rest"], shift,
                *raster_graph.view_inputs(cam, dev, torch.float32, cfg))
        graphed, make = timed(lambda: _graphs.make_graphed(fn, args, warmup=raster_graph._WARMUP))
        keep = torch.cuda.empty_cache
        torch.cuda.empty_cache = lambda: None
        try:
            _, make_kept = timed(lambda: _graphs.make_graphed(fn, args, warmup=raster_graph._WARMUP))
        finally:
            torch.cuda.empty_cache = keep
        _, check = timed(lambda: check_replay(graphed, fn, args))
        print(f"n={n}: capture + check {whole:.1f} ms (first 10 iterations after it {first:.2f} ms each, then "
              f"{later:.2f}); make_graphed {make:.1f} ms, with the cache kept {make_kept:.1f}; check {check:.1f} ms",
              flush=True)

    for r in range(a.rounds):
        one_round(a.n + r * a.grow)


if __name__ == "__main__":
    main()
