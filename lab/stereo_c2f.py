"""Lab (nothing imports it): a coarse-to-fine plane sweep against the fit's (#60: the initial surfels take 10.8 s of
DTU's 101 s on an H200, the goal is 3 s; sweeping at fewer pixels lost DTU's held-out PSNR, design/decisions.md).

Coarse to fine keeps every full-resolution pixel: each family (planes facing the camera, level planes) is swept at
half the resolution over all its planes, the winners' parameters are brought up to full resolution (nearest, small
holes filled from their neighbours), and the full-resolution sweep then scores only ``--offsets`` hypotheses per
pixel around them (a per-pixel family: inverse depth for the facing planes, height for the level ones). The rest
(winner per pixel, forward-backward check, normals) is the fit's own code. For each scene of the peers' set with
ground truth: seconds, confirmed points, their distance to the truth (median, share within 0.5 % of the region's
diagonal) and the share of training pixels no point explains, for the fit's sweep and for this one.

    PYTHONPATH=. .venv/bin/python lab/stereo_c2f.py [--scenes bunny_env chair_env mug_torus_env] [--views 24]
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))

from wtopo.geometry import mvs as M  # noqa: E402


class _AroundFronto:
    """Per pixel, inverse depths ``inv0 + params`` (``inv0`` 0: no hypothesis there)."""

    def __init__(self, inv0: torch.Tensor, params: torch.Tensor):
        self.inv0, self.params = inv0, params
        self.shape = tuple(inv0.shape)

    def _d(self, inv):
        return torch.where((self.inv0 > 0) & (inv > 0), 1.0 / inv.clamp_min(1e-12), -1.0)

    def depth(self, p):
        return self._d(self.inv0[None] + p[:, None, None])

    def depth_at(self, p):
        return self._d(self.inv0 + p)


class _AroundLevel:
    """Per pixel, heights ``h0 + params`` of level planes (``valid`` False: no hypothesis there)."""

    def __init__(self, level: "M._Level", h0: torch.Tensor, valid: torch.Tensor, params: torch.Tensor):
        self.level, self.h0, self.valid, self.params = level, h0, valid, params
        self.shape = tuple(h0.shape)

    def _d(self, h):
        lv = self.level
        b = torch.where(lv.b.abs() < 1e-6, 1e-6, lv.b)
        return torch.where(self.valid, lv._valid((h - lv.a) / b), -1.0)

    def depth(self, p):
        return self._d(self.h0[None] + p[:, None, None])

    def depth_at(self, p):
        return self._d(self.h0 + p)


def _up(x: torch.Tensor, H: int, W: int, valid: torch.Tensor, fill: int = 2, smooth: int = 3):
    """A coarse map with holes (``valid`` False) filled from up to ``fill`` pixels around, smoothed by ``smooth``
    3 x 3 means and brought up bilinearly: a window's pixels must share about one plane, as in the full sweep, so
    the field must not jump from pixel to pixel (nearest upsampling's 2 x 2 steps lost a sixth of the points)."""
    x, v = x.clone(), valid.float()
    for _ in range(fill):  # fill holes by the mean of valid neighbours
        s = F.avg_pool2d((x * v)[None, None], 3, 1, 1)[0, 0]
        n = F.avg_pool2d(v[None, None], 3, 1, 1)[0, 0]
        x = torch.where(v > 0, x, torch.where(n > 0, s / n.clamp_min(1e-9), x))
        v = torch.maximum(v, (n > 0).float())
    for _ in range(smooth):
        s = F.avg_pool2d((x * v)[None, None], 3, 1, 1)[0, 0]
        n = F.avg_pool2d(v[None, None], 3, 1, 1)[0, 0]
        x = torch.where(v > 0, s / n.clamp_min(1e-9), x)
    xu = F.interpolate((x * v)[None, None], size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    vu = F.interpolate(v[None, None], size=(H, W), mode="bilinear", align_corners=False)[0, 0]
    return xu / vu.clamp_min(1e-9), vu > 0.999


class _Nothing:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return None


class _NoThresholds:
    """The coarse pass keeps every pixel's best hypothesis (the fine pass applies the fit's thresholds)."""

    def __enter__(self):
        self.saved = M._MIN_SCORE, M._MIN_TEXTURE
        M._MIN_SCORE, M._MIN_TEXTURE = -0.999, 0.0

    def __exit__(self, *exc):
        M._MIN_SCORE, M._MIN_TEXTURE = self.saved


def c2f_points(cameras, images, lower, upper, *, near, device="cpu", max_views=None, offsets=9, all_coarse=True,
               edges=False, sparse=0):
    """:func:`wtopo.geometry.mvs.plane_sweep_points` with each family swept coarse to fine (module docstring)."""
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    if max_views is not None and len(cameras) > max_views:
        pick = np.unique(np.round(np.linspace(0, len(cameras) - 1, int(max_views))).astype(np.int64))
        cameras = [cameras[i] for i in pick]
        images = [images[i] for i in pick]
    dev = torch.device(device)
    tcams = [M.TorchCam(c, dev) for c in cameras]
    grays = [M.gray(torch.as_tensor(images[i], dtype=torch.float32).to(dev)) for i in range(len(cameras))]
    coarse_cams = [c.scaled(0.5) for c in cameras]
    ccams = [M.TorchCam(c, dev) for c in coarse_cams]
    cgrays = [F.interpolate(g[None, None], size=(c.height, c.width), mode="area")[0, 0]
              for g, c in zip(grays, coarse_cams)]
    nbrs = M.select_neighbours(cameras, 0.5 * (lower + upper))
    up = M.capture_up(cameras)
    corners = np.array([[(lower, upper)[b >> a & 1][a] for a in range(3)] for b in range(8)])
    depths, level = [], []
    half = (offsets - 1) // 2
    with torch.no_grad():
        for i, ref in enumerate(tcams):
            if not nbrs[i]:
                depths.append(torch.zeros(ref.H, ref.W, device=dev))
                level.append(torch.zeros(ref.H, ref.W, dtype=torch.bool, device=dev))
                continue
            srcs = [tcams[j] for j in nbrs[i]]
            csrcs = [ccams[j] for j in nbrs[i]]
            cref = ccams[i]
            lo, hi = M._depth_range(cameras[i], lower, upper, near)
            n_full = M._n_planes(ref, srcs[0], lo, hi)
            n_c = M._n_planes(cref, csrcs[0], lo, hi)
            src_gray = torch.stack([grays[j] for j in nbrs[i]])
            csrc_gray = torch.stack([cgrays[j] for j in nbrs[i]])
            # planes facing the camera: coarse over all, fine around the coarse winner (steps of the fine sweep)
            fr = M._Fronto(lo, hi, n_c, dev)
            fr.shape = (cref.H, cref.W)
            with _NoThresholds() if all_coarse else _Nothing():
                dc, _ = M._sweep(cref, csrcs, cgrays[i], csrc_gray, fr)
            inv_c, ok_c = _up(torch.where(dc > 0, 1.0 / dc.clamp_min(1e-12), 0.0), ref.H, ref.W, dc > 0)
            step = (1.0 / lo - 1.0 / hi) / max(n_full - 1, 1)
            params = torch.arange(-half, half + 1, device=dev, dtype=torch.float32) * step
            d, score = M._sweep(ref, srcs, grays[i], src_gray, _AroundFronto(torch.where(ok_c, inv_c, 0.0), params))
            if edges:  # at a depth edge the smoothed field lies between the two sides: try each side too
                invc = torch.where(dc > 0, 1.0 / dc.clamp_min(1e-12), 0.0)
                for side in (F.max_pool2d(invc[None, None], 5, 1, 2)[0, 0],
                             -F.max_pool2d(-torch.where(invc > 0, invc, 1e9)[None, None], 5, 1, 2)[0, 0]):
                    side = torch.where(side < 1e8, side, 0.0)
                    inv_s, ok_s = _up(side, ref.H, ref.W, side > 0, smooth=0)
                    ds, ss = M._sweep(ref, srcs, grays[i], src_gray,
                                      _AroundFronto(torch.where(ok_s, inv_s, 0.0), params))
                    better = ss > score
                    d, score = torch.where(better, ds, d), torch.where(better, ss, score)
            if sparse > 1:  # every sparse-th plane of the full sweep too: for pixels whose coarse winner is wrong
                fs = M._Fronto(lo, hi, max(2, n_full // sparse), dev)
                fs.shape = (ref.H, ref.W)
                ds, ss = M._sweep(ref, srcs, grays[i], src_gray, fs)
                better = ss > score
                d, score = torch.where(better, ds, d), torch.where(better, ss, score)
            won = torch.zeros_like(d, dtype=torch.bool)
            if up is not None:
                h = corners @ up
                hl = (float(h.min()), float(h.max()))
                lc = M._Level(cref, up, hl, lo, hi, n_c)
                with _NoThresholds() if all_coarse else _Nothing():
                    d2c, _ = M._sweep(cref, csrcs, cgrays[i], csrc_gray, lc)
                h_c = torch.where(d2c > 0, lc.a + lc.b * d2c, 0.0)  # the winner's height per coarse pixel
                h_f, okh = _up(h_c, ref.H, ref.W, d2c > 0)
                lf = M._Level(ref, up, hl, lo, hi, n_full)
                hstep = (hl[1] - hl[0]) / max(n_full - 1, 1)
                hparams = torch.arange(-half, half + 1, device=dev, dtype=torch.float32) * hstep
                d2, score2 = M._sweep(ref, srcs, grays[i], src_gray, _AroundLevel(lf, h_f, okh, hparams))
                won = score2 > score
                d = torch.where(won, d2, d)
            depths.append(d)
            level.append(won & (d > 0))
    return M.confirmed_points(tcams, images, nbrs, depths, level, up)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=["bunny_env", "chair_env", "mug_torus_env"])
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--offsets", type=int, default=9)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--coarse-thresholds", action="store_true", help="the coarse pass keeps only confident winners")
    ap.add_argument("--no-full", action="store_true", help="skip the fit's sweep")
    ap.add_argument("--edges", action="store_true", help="also sweep around each side of a coarse depth edge")
    ap.add_argument("--sparse", type=int, default=0, help="also sweep every N-th plane of the full sweep")
    a = ap.parse_args()

    import scenes as peer_scenes
    import trimesh

    from wtopo import scenes as wtopo_scenes
    from wtopo.fitting.background import uncovered_pixels
    from wtopo.fitting.scene_kind import analyse_layout

    torch.manual_seed(0)
    for name in a.scenes:
        scene = (peer_scenes.load(name) if name in peer_scenes.names() else wtopo_scenes.load(name)).normalized()
        layout = analyse_layout(scene)
        pts_gt, _ = trimesh.sample.sample_surface(scene.gt_mesh, 2_000_000, seed=0)
        tree = cKDTree(pts_gt)
        diag = float(np.linalg.norm(np.asarray(layout.roi_upper) - np.asarray(layout.roi_lower)))
        for how in (("c2f",) if a.no_full else ("full", "c2f")):
            t = time.perf_counter()
            if how == "full":
                pts = M.plane_sweep_points(scene.cameras, scene.images, layout.roi_lower, layout.roi_upper,
                                           near=layout.near, device=a.device, max_views=a.views).points
            else:
                pts = c2f_points(scene.cameras, scene.images, layout.roi_lower, layout.roi_upper, near=layout.near,
                                 device=a.device, max_views=a.views, offsets=a.offsets,
                                 all_coarse=not a.coarse_thresholds, edges=a.edges,
                                 sparse=a.sparse).points
            sec = time.perf_counter() - t
            d, _ = tree.query(pts, workers=-1)
            unc = uncovered_pixels(scene.cameras, pts, device=a.device)
            print(json.dumps({"scene": name, "sweep": how, "s": round(sec, 1), "points": len(pts),
                              "median_dist_pct": round(100 * float(np.median(d)) / diag, 4),
                              "within_0.5pct": round(float(np.mean(d < 0.005 * diag)), 4),
                              "uncovered": round(float(np.mean([u.float().mean().item() for u in unc])), 4)}),
                  flush=True)


if __name__ == "__main__":
    main()
