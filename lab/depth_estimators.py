# SPDX-License-Identifier: Apache-2.0
"""Is the fused depth behind the surface because of the depth estimator or because of where the surfels sit
(#59, after lab/depth_bias.py)?

    .venv/bin/python lab/depth_estimators.py RUN      # RUN: a CPU fit of the built-in bunny, polish.iterations=0

On 400 random pixels inside the true mask of every third training view, the float64 reference renderer's
contributions (tests/reference/rasterize.py's geometry) give several per-pixel depths, each minus the true
z-depth, as % of the true mesh's diagonal (+: behind the surface):
  median      the renderer's: the contribution where the transmittance crosses 0.5, in centre-depth order
  median_pp   the same, with the contributions sorted by their depth at this pixel
  interp      between the crossing contribution and the one before it, by how much of its opacity the crossing
              takes
  argmax_w    the contribution of largest blending weight (where the surfel itself lies)
  expected    the alpha-weighted mean
and the argmax_w error by quartile of that surfel's larger scale; and how many contributions a pixel composites
before its transmittance crosses 0.5, and how many weigh more than 0.05. Nothing imports it.
"""

import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests"))
from reference import rasterize as ref  # noqa: E402

from wtopo import scenes  # noqa: E402
from wtopo.io.ply import read_surfels_ply  # noqa: E402

ESTIMATORS = ("median", "median_pp", "interp", "argmax_w", "expected")


def _composite(z, a, order):
    """Front-to-back compositing in ``order`` with the renderer's early stop: depths, opacities, transmittance
    before each contribution, weights and the index of the contribution where the transmittance crosses 0.5."""
    z, a = z[order], a[order]
    tb = np.concatenate([[1.0], np.cumprod(1 - a)[:-1]])
    go_on = np.cumsum(tb * (1 - a) < 1e-4) == 0  # alpha <= 0.99: the first contribution always stays
    z, a, tb = z[go_on], a[go_on], tb[go_on]
    w = a * tb
    return z, a, tb, w, int(np.flatnonzero(tb > 0.5).max())


def main(run: str) -> None:
    train = scenes.load("bunny").split("train")
    s = read_surfels_ply(os.path.join(run, "surfels.ply"))
    with open(os.path.join(run, "plan.json")) as f:
        sigma = float(json.load(f)["filter_sigma"]["value"])
    lo, hi = train.gt_mesh.bounds
    diag = float(np.linalg.norm(hi - lo))

    def t(x):
        return torch.as_tensor(np.asarray(x), dtype=torch.float64)

    means, quats, scales, opac = t(s.means), t(s.quats), t(s.scales), t(s.opacities)
    tu, tv, nrm = ref.quat_axes_ref(quats)
    U, V = tu / scales[:, 0:1].clamp_min(1e-30), tv / scales[:, 1:2].clamp_min(1e-30)
    err = {k: [] for k in ESTIMATORS}
    size, crossing, layers = [], [], []
    rng = np.random.default_rng(0)
    for vi in range(0, len(train.cameras), 3):
        cam = train.cameras[vi]
        gt = np.asarray(train.depths[vi]).reshape(-1)
        inside = (np.asarray(train.masks[vi]).reshape(-1) > 0.5) & (gt > 0)
        pix = torch.as_tensor(rng.choice(np.flatnonzero(inside), 400, replace=False))
        pc = means @ t(cam.R).T + t(cam.t)
        zc = pc[:, 2]
        near = 0.05 * float(zc[zc > 0].median())  # the renderer's default near plane (RasterConfig.near_fraction)
        d = cam.pixel_rays("cpu", torch.float64)[1].reshape(-1, 3)[pix]
        a0 = t(cam.center) - means
        dn = (d[:, None, :] * nrm[None]).sum(-1)
        parallel = dn.abs() <= 1e-12
        hit = -(a0 * nrm).sum(-1)[None] / torch.where(parallel, torch.ones_like(dn), dn)
        x = a0[None] + hit[..., None] * d[:, None, :]
        rho3 = (x * U[None]).sum(-1) ** 2 + (x * V[None]).sum(-1) ** 2
        rho3 = torch.where(parallel | ~torch.isfinite(rho3), torch.full_like(rho3, 1e30), rho3)
        m2 = ref.project_ref(cam, pc, t(cam.K), [0.0] * 5)
        pxy = torch.stack([(pix % cam.width).double() + 0.5, (pix // cam.width).double() + 0.5], -1)
        rho2 = ((pxy[:, None] - m2[None]) ** 2).sum(-1) / sigma**2
        object_space = rho3 <= rho2 + 1e-9
        z = torch.where(object_space, hit, zc[None].expand_as(hit))
        alpha = torch.clamp(opac[None] * torch.exp(-0.5 * torch.where(object_space, rho3, rho2)), max=0.99)
        ok = (alpha >= 1 / 255) & (z >= near) & (zc > near)[None]
        true = gt[pix.numpy()]
        for p in range(len(pix)):
            idx = torch.nonzero(ok[p]).flatten().numpy()
            if len(idx) == 0:
                continue
            zz, aa, cz = z[p, idx].numpy(), alpha[p, idx].numpy(), zc[idx].numpy()
            order = np.argsort(cz, kind="stable")
            zs, a_s, tb, w, k = _composite(zz, aa, order)
            if tb[-1] * (1 - a_s[-1]) > 0.5:  # less than 0.5 opacity: the fusion leaves the pixel out
                continue
            err["median"].append(zs[k])
            crossing.append(k + 1)
            layers.append(int((w > 0.05).sum()))
            if k > 0:
                frac = (tb[k] - 0.5) / max(tb[k] * a_s[k], 1e-9)
                err["interp"].append(zs[k - 1] + (zs[k] - zs[k - 1]) * frac)
            else:
                err["interp"].append(zs[0])
            err["argmax_w"].append(zs[np.argmax(w)])
            err["expected"].append((w * zs).sum() / w.sum())
            zs2, _, _, _, k2 = _composite(zz, aa, np.argsort(zz, kind="stable"))
            err["median_pp"].append(zs2[k2])
            for key in ESTIMATORS:
                err[key][-1] -= true[p]
            size.append(float(scales[idx[order][: len(w)][np.argmax(w)]].max()))
    for key in ESTIMATORS:
        e = np.array(err[key]) / diag * 100
        print(f"{key:10s} {len(e)} pixels: mean {e.mean():+.4f} median {np.median(e):+.4f} mean |e| "
              f"{np.abs(e).mean():.4f} (% of the diagonal, + behind)")
    print(f"the transmittance crosses 0.5 at contribution {np.quantile(crossing, [0.1, 0.5, 0.9])} (10/50/90 %); "
          f"contributions of weight > 0.05: {np.quantile(layers, [0.1, 0.5, 0.9])}")
    size = np.array(size)
    e = np.array(err["argmax_w"]) / diag * 100
    for q0, q1 in [(0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.0)]:
        a, b = np.quantile(size, [q0, q1])
        m = (size >= a) & (size <= b)
        print(f"argmax_w, largest scale {a:.4f}-{b:.4f}: mean {e[m].mean():+.4f} median {np.median(e[m]):+.4f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
