# SPDX-License-Identifier: Apache-2.0
"""PGSR's multi-view geometric consistency as a lab term (#59: DTU's scene mesh is rough and holed at the CUDA plan's
grid, design/decisions.md "Not changed: the scene fusion's grid and the face rule's tolerance").

    GEO_CONSISTENCY=W (fit_patches.py)

From where the multi-view NCC term starts (mid warm-up) and outside the polish, each step also renders one of the view's
multi-view neighbours (drawn per iteration) and, for ``_PIXELS`` pixels drawn over the reference view (those both views
cover count): the point at the reference's median depth, projected into the neighbour; the neighbour's median depth
there (bilinear), that point projected back into the reference. The term is PGSR's: the mean over pixels whose round
trip ends within ``_MAX_PX`` pixels of ``exp(-e).detach() * e``, e the round trip's length in pixels, times W (PGSR:
0.03). Gradients reach both renders' depths. Pinhole cameras only (the round trip ignores distortion). Costs a second
render (forward and backward) per step. Does nothing where the plan leaves the multi-view term out (an untextured
capture).
"""

import random

import torch

from wtopo.fitting import objective as O
from wtopo.fitting.config import stage_iteration
from wtopo.fitting.stages import Stage

_PIXELS = 4096
_MAX_PX = 1.0


def _pinhole(cam, device):
    """The camera's K, R, t as float32 tensors on ``device``, made once per camera (Camera.cached)."""
    return cam.cached(("geo_pinhole", str(device)), lambda: tuple(
        torch.as_tensor(x, dtype=torch.float32, device=device) for x in (cam.K, cam.R, cam.t)))


def _project(X, K, R, t):
    p = X @ R.T + t
    z = p[:, 2].clamp_min(1e-6)
    u = K[0, 0] * p[:, 0] / z + K[0, 1] * p[:, 1] / z + K[0, 2]
    v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return u, v, p[:, 2]


def _backproject(u, v, d, K, R, t):
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    pc = torch.stack([x * d, y * d, d], dim=1)
    return (pc - t) @ R


def geo_term(depth_r, alpha_r, cam_r, depth_n, alpha_n, cam_n, gen) -> torch.Tensor:
    """The term's value (unweighted) for one reference view and one neighbour; 0 with no pixel that counts."""
    dev = depth_r.device
    H, W = depth_r.shape
    idx = torch.randint(0, H * W, (_PIXELS,), generator=gen, device=dev)
    v0, u0 = (idx // W).float() + 0.5, (idx % W).float() + 0.5
    d = depth_r.reshape(-1)[idx]
    ok = (alpha_r.reshape(-1)[idx].detach() >= 0.5) & (d.detach() > 0)
    Kr, Rr, tr = _pinhole(cam_r, dev)
    Kn, Rn, tn = _pinhole(cam_n, dev)
    X = _backproject(u0, v0, d, Kr, Rr, tr)
    un, vn, zn = _project(X, Kn, Rn, tn)
    Hn, Wn = depth_n.shape
    grid = torch.stack([un / Wn * 2 - 1, vn / Hn * 2 - 1], dim=1).view(1, 1, -1, 2)
    dn = torch.nn.functional.grid_sample(depth_n[None, None], grid, mode="bilinear", align_corners=False,
                                         padding_mode="border").view(-1)
    an = torch.nn.functional.grid_sample(alpha_n.detach()[None, None], grid, mode="bilinear", align_corners=False,
                                         padding_mode="border").view(-1)
    ok = ok & (zn.detach() > 0) & (un.detach() >= 0) & (un.detach() < Wn) & (vn.detach() >= 0) & (vn.detach() < Hn)
    ok = ok & (dn.detach() > 0) & (an >= 0.5)
    X2 = _backproject(un, vn, dn, Kn, Rn, tn)
    u2, v2, _ = _project(X2, Kr, Rr, tr)
    e = torch.sqrt((u2 - u0) ** 2 + (v2 - v0) ** 2 + 1e-12)
    keep = ok & (e.detach() < _MAX_PX)
    w = torch.exp(-e).detach() * keep
    return (w * e).sum() / keep.sum().clamp_min(1)


def install(weight: float | None = None) -> None:
    import os

    wgt = float(os.environ.get("GEO_CONSISTENCY", 0.03)) if weight is None else float(weight)
    call = O.Objective.__call__
    gens = {}

    def patched(self, stage, it, vi, surfels, proxy, **kw):
        terms = call(self, stage, it, vi, surfels, proxy, **kw)
        mv = self.multiview
        late = stage != Stage.WARMUP
        if (stage == Stage.POLISH or mv is None or not mv.has_neighbours(vi)
                or not (late or it >= stage_iteration(O._MULTIVIEW_START, self.warmup_end))):
            return terms
        out = terms.render
        dev = out.alpha.device
        g = gens.get(dev) or gens.setdefault(dev, torch.Generator(dev))
        seed = 1_000_003 * (int(self.cfg.runtime.seed) + 101) + it  # not the NCC term's pixel stream
        g.manual_seed(seed)
        nb = mv.neighbours[vi]
        n = nb[random.Random(seed).randrange(len(nb))]  # drawn on the host: no device read per step
        with self.timers("render"):
            out_n = self.render(surfels, self.train.cameras[n])
        with self.timers("losses"):
            terms.losses["geo"] = wgt * geo_term(out.median_depth, out.alpha, self.train.cameras[vi],
                                                 out_n.median_depth, out_n.alpha, self.train.cameras[n], g)
        return terms

    O.Objective.__call__ = patched
