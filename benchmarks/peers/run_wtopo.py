# SPDX-License-Identifier: Apache-2.0
"""wtopo on an exchange folder: fit, render the held-out views, write a result folder.

python benchmarks/peers/run_wtopo.py EXCH OUT [--device cuda:0] [--no-loop] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _result import Clock, write_result  # noqa: E402
from exchange import load  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exchange")
    ap.add_argument("out")
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--no-loop", action="store_true", help="no co-evolution with the proxy mesh")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--label", default=None)
    a = ap.parse_args(argv)

    import wtopo
    from wtopo.cli import _apply_set
    from wtopo.fitting.config import FitConfig

    ex = load(a.exchange)
    sets = list(a.set) + [f"runtime.device={a.device}"]
    if a.no_loop:
        sets.append("coevolution.enabled=false")
    cfg = FitConfig()
    for item in sets:
        _apply_set(cfg, item)
    clock = Clock()
    scene = ex.scene()
    res = wtopo.fit(scene, cfg, out_dir=os.path.join(a.out, "run"), progress=False)
    run = clock.stop()
    # the held-out views, rendered as the fit renders them (internal frame, the fit's screen-space filter: the
    # rasterizer's own default is 2DGS's wider one)
    inner = scene.normalized()
    raster = wtopo.ops.RasterConfig(filter_sigma=res.plan.filter_sigma)
    s = res.surfels
    bg = torch.tensor(scene.background if scene.background is not None else (0.0, 0.0, 0.0), dtype=torch.float32,
                      device=s.means.device)
    renders = []
    with torch.no_grad():
        for i in ex.test:
            out = wtopo.ops.rasterize_surfels(s.means, s.quats, s.scales, s.opacities, s.sh, inner.cameras[i],
                                              sh_degree=s.sh_degree, background=bg, config=raster)
            renders.append(out.rgb.clamp(0, 1).cpu().numpy())
    run.update({"iterations": res.report.get("iterations"), "surfels": int(s.means.shape[0]),
                "settings": sets, "own_report": {k: res.report.get(k) for k in ("psnr", "ssim", "chamfer", "f_score")}})
    write_result(a.out, system=a.label or ("wtopo (no loop)" if a.no_loop else "wtopo"), mesh=res.mesh,
                 renders=np.stack(renders), run=run)


if __name__ == "__main__":
    main()
