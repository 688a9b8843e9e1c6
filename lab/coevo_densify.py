"""Lab (nothing imports it): clone/split by screen-space gradient during the first part of the co-evolution too,
as 3DGS / 2DGS / gsplat densify by gradient through half their schedule. The package densifies only in the
warm-up, whose surfels the TSDF re-initialisation then replaces by one per face of its mesh
(``plan.reinit_faces``, about 64,000 on the 64-view chair), so the co-evolution renders with that many surfels to
the end. The patch accumulates the means' screen-space gradients in the co-evolution as well and runs
``densify.clone_and_split`` (the package's threshold, growth cap and ``runtime.max_surfels``) every density interval
from the co-evolution's first interval until ``FRACTION`` of it (env ``COEVO_DENSIFY_FRACTION``, default 0.5),
with the opacity prune.

    python3 lab/coevo_densify.py EXCH OUT [--set KEY=VALUE ...]     # benchmarks/peers/run_wtopo.py's arguments
"""
import os
import runpy
import sys

import torch

import wtopo.fitting._strategy as st
from wtopo.fitting import densify as dens
from wtopo.fitting.stages import ROI_EXTENT, Stage

FRACTION = float(os.environ.get("COEVO_DENSIFY_FRACTION", "0.5"))
_post, _end = st.DensityStrategy.step_post_backward, st.DensityStrategy.step_end


def step_post_backward(self, surfels, info):
    _post(self, surfels, info)
    out, cam = info.render, info.camera
    if info.stage == Stage.COEVOLUTION and out.means2d.grad is not None:
        with torch.no_grad():
            dens.accumulate_gradients(surfels, out.means2d.grad, out.visibility > 0, cam.width, cam.height)


def step_end(self, stage, it, surfels):
    if stage != Stage.COEVOLUTION:
        return _end(self, stage, it, surfels)
    k = it - self.warmup_end
    every = self._interval()
    if not (self.densify and 0 < k < FRACTION * self.cfg.coevolution.iterations and k % every == 0):
        return False
    with self.timers("densify"):
        c, sp = dens.clone_and_split(surfels, ROI_EXTENT, self.cfg.runtime.max_surfels, self.gen)
        self.record("densify", cloned=c, split=sp, gap=self.gap)
        removed = dens.prune_by_opacity(surfels, st.PRUNE_OPACITY)
    return bool(c or sp or removed)


st.DensityStrategy.step_post_backward = step_post_backward
st.DensityStrategy.step_end = step_end

if __name__ == "__main__":
    sys.argv = [os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "peers", "run_wtopo.py"),
                *sys.argv[1:]]
    runpy.run_path(sys.argv[0], run_name="__main__")
