# SPDX-License-Identifier: Apache-2.0
"""The TSDF stages fuse no rendered depth outside the view's mask (#59: wtopo's meshes lie inside the surface,
design/decisions.md).

    FUSION_MASKED=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]

With lab/ring_blind.py the photometric and mask terms no longer pull the silhouette in, and nothing stops the
surfels' tails from covering the 1-px ring outside the mask either: the thin chair's legs and slats fuse that much
wider (CPU +37-38 %). 2DGS's TSDF fuses no depth outside the mask; here neither the re-initialisation's nor the final
fusion does: a pixel outside the view's mask reads no depth (zero, as where the rendered opacity is below the
threshold). ``install()`` registers each fit's training masks by camera when the fit starts and patches the
``render_depths`` that ``wtopo.fitting._final_mesh`` and ``wtopo.fitting._reinit`` call (lab/fit_patches.py's
FUSION_MASKED). Scenes without masks are unchanged.
"""

import numpy as np

_MASKS: dict[int, np.ndarray] = {}


def install() -> None:
    """Patch the fit so that its TSDF stages fuse the rendered depth inside the masks only."""
    from wtopo.fitting import _final_mesh, _reinit, loop

    init = loop.FitRun.__init__

    def registering_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        _MASKS.clear()
        masks = self.train.masks
        if masks is not None:
            for cam, m in zip(self.train.cameras, masks):
                _MASKS[id(cam)] = m.detach().cpu().numpy() >= 0.5 if m.dtype != bool else m.cpu().numpy()

    loop.FitRun.__init__ = registering_init
    render_depths = _final_mesh.render_depths

    def masked_render_depths(render, surfels, cameras):
        depths, colors = render_depths(render, surfels, cameras)
        out = []
        for cam, d in zip(cameras, depths):
            m = _MASKS.get(id(cam))
            out.append(d if m is None or m.shape != d.shape else np.where(m, d, 0.0).astype(d.dtype))
        return out, colors

    _final_mesh.render_depths = masked_render_depths
    _reinit.render_depths = masked_render_depths
