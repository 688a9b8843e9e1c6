"""Lab (nothing imports it): where the surface that DTU's held-out view 40 draws over the backdrop sits.

Takes the surfels that ``lab/dtu_view40.py --save PATH`` wrote and renders view 40 (the fit's filter). Band pixels are
those where the photograph is dark (grey < 0.15) and the render bright (> 0.5). Table pixels are bright in both, in
the image's left 90 columns. Both are back-projected from the rendered median depth (internal frame). A plane is fitted
to the table points, and the script prints the band points' signed distances to it (positive: the cameras' side).
Each band point is then projected into every training view, with what that view's photograph shows there: bright
(the white table, where a surface at that place is photometrically invisible), dark, or outside the frame.

    PYTHONPATH=. .venv/bin/python lab/dtu_band.py /tmp/surfels.pt [--data ../shared/data/dtu_scan24]
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from dtu_view40 import peers_split  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("surfels")
    ap.add_argument("--data", default=os.path.join(HERE, "..", "..", "shared", "data", "dtu_scan24"))
    ap.add_argument("--view", type=int, default=40)
    ap.add_argument("--culprits", action="store_true", help="also the surfels centred on the band (culprits())")
    a = ap.parse_args()
    if a.culprits:
        culprits(a.surfels, a.data, a.view)
    from wtopo import ops

    d = {k: v.detach() if torch.is_tensor(v) else v for k, v in torch.load(a.surfels).items()}
    scene, _ = peers_split(a.data)
    inner = scene.normalized()
    cam = inner.cameras[a.view]
    raster = ops.RasterConfig(filter_sigma=d["filter_sigma"])
    with torch.no_grad():
        r = ops.rasterize_surfels(d["means"], d["quats"], d["scales"], d["opacities"], d["sh"], cam,
                                  sh_degree=d["sh_degree"], config=raster)
    photo = inner.images[a.view].numpy().mean(-1)
    render = r.rgb.clamp(0, 1).numpy().mean(-1)
    depth = r.median_depth.numpy()
    ro, rd = cam.pixel_rays("cpu")
    pts = (ro + rd * torch.as_tensor(depth)[..., None]).numpy()
    h, w = photo.shape
    cols = np.arange(w)[None, :] < 90
    band = (photo < 0.15) & (render > 0.5) & cols
    table = (photo > 0.6) & (render > 0.6) & cols & (r.alpha.numpy() > 0.9)
    print(f"view {a.view}: {band.sum()} band pixels, {table.sum()} table pixels (left 90 columns)")
    if band.sum() == 0 or table.sum() < 10:
        return
    tp = pts[table]
    c = tp.mean(0)
    _, _, vt = np.linalg.svd(tp - c)
    n = vt[2]
    if np.dot(n, cam.center - c) < 0:
        n = -n
    res = (tp - c) @ n
    bp = pts[band]
    dist = (bp - c) @ n
    print(f"table plane fit: rms {np.sqrt((res ** 2).mean()):.4f}; band points' distance to it: median "
          f"{np.median(dist):.4f}, 10-90 % {np.percentile(dist, 10):.4f} .. {np.percentile(dist, 90):.4f} "
          "(internal units; the cube is 1)")
    print(f"band depth median {np.median(depth[band]):.3f}, table depth median {np.median(depth[table]):.3f}")
    bright = dark = out = 0
    per_view = []
    for i in scene.train_indices:
        ci = inner.cameras[i]
        uv, z = ci.project(bp)
        img = inner.images[i].numpy().mean(-1)
        hi, wi = img.shape
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < wi) & (uv[:, 1] >= 0) & (uv[:, 1] < hi)
        g = np.zeros(len(bp))
        g[inside] = img[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        b, k = int((inside & (g > 0.6)).sum()), int((inside & (g < 0.15)).sum())
        bright, dark, out = bright + b, dark + k, out + int((~inside).sum())
        per_view.append((i, b, k))
    print(f"band points in the training views: on bright pixels {bright}, on dark {dark}, outside the frame {out}")
    print("views where the band lands on dark pixels:", [(i, k) for i, b, k in per_view if k > 0][:20])


def culprits(path, data, view=40):
    """The surfels whose centres project onto the band (dilated 3 px) in ``view``: the band's brightness without them,
    and where they sit (distance to the table plane, opacity, colour) and how many training views see them."""
    import torch.nn.functional as F

    from wtopo import ops
    from wtopo.fitting.background import BackgroundState  # noqa: F401  (the frame is the fit's internal one)

    d = {k: v.detach() if torch.is_tensor(v) else v for k, v in torch.load(path).items()}
    scene, _ = peers_split(data)
    inner = scene.normalized()
    cam = inner.cameras[view]
    raster = ops.RasterConfig(filter_sigma=d["filter_sigma"])

    def render(keep, c=cam):
        with torch.no_grad():
            return ops.rasterize_surfels(d["means"][keep], d["quats"][keep], d["scales"][keep], d["opacities"][keep],
                                         d["sh"][keep], c, sh_degree=d["sh_degree"], config=raster)

    n = len(d["means"])
    allk = torch.ones(n, dtype=torch.bool)
    r = render(allk)
    photo = inner.images[view].numpy().mean(-1)
    img = r.rgb.clamp(0, 1).numpy().mean(-1)
    h, w = photo.shape
    band = torch.as_tensor((photo < 0.15) & (img > 0.5) & (np.arange(w)[None, :] < 90))
    dil = F.max_pool2d(band[None, None].float(), 7, 1, 3)[0, 0] > 0
    uv, z = cam.project(d["means"].double().numpy())
    ui, vi = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (z > 0) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    on = np.zeros(n, dtype=bool)
    on[inside] = dil.numpy()[vi[inside], ui[inside]]
    on_t = torch.as_tensor(on)
    r2 = render(~on_t)
    img2 = r2.rgb.clamp(0, 1).numpy().mean(-1)
    print(f"{on.sum()} surfels centred on the band; the band's mean grey {img[band.numpy()].mean():.3f} with them, "
          f"{img2[band.numpy()].mean():.3f} without (photo {photo[band.numpy()].mean():.3f})")
    seen = torch.zeros(n, dtype=torch.int64)
    for i in scene.train_indices:
        seen += (render(allk, inner.cameras[i]).visibility > 0).long()
    op = d["opacities"][on_t]
    big = op > 0.3
    print(f"their opacity: median {op.median():.3f}, > 0.3: {int(big.sum())}; training views that see them: median "
          f"{seen[on_t].float().median():.0f}, min {seen[on_t].min()}, max {seen[on_t].max()}; depth in view {view}: "
          f"median {np.median(z[on]):.3f}")
    dc = d["sh"][on_t][:, 0] * 0.28209479177387814 + 0.5
    print(f"their DC colour (grey): median {dc.mean(-1).median():.3f}")
    return on


if __name__ == "__main__":
    main()
