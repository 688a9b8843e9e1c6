# SPDX-License-Identifier: Apache-2.0
"""Run inside a peer's checkout: render a trained model in the exchange folder's held-out views with the
checkout's own renderer (SH colours, the training background), as its ``render.py`` does.

python _peer_views.py {2dgs,pgsr} MODEL ITERATION EXCH OUT.npz

``2dgs``: a 2d-gaussian-splatting checkout. ``pgsr``: a PGSR checkout (``pgsr_dpsr`` or its earlier plain
PGSR commit; no exposure model).
"""

import inspect
import math
import os
import sys
from types import SimpleNamespace

import numpy as np
import torch

sys.path.insert(0, os.getcwd())
from _result import read_json  # noqa: E402  (this script's folder is on the path too)
from gaussian_renderer import render  # noqa: E402
from scene.cameras import Camera  # noqa: E402
from scene.gaussian_model import GaussianModel  # noqa: E402


def _camera(peer: str, i: int, K, w2c, W: int, H: int, exch: str):
    fovx, fovy = 2 * math.atan(W / (2 * K[0, 0])), 2 * math.atan(H / (2 * K[1, 1]))
    common = dict(colmap_id=i, R=w2c[:3, :3].T, T=w2c[:3, 3], FoVx=fovx, FoVy=fovy, image_name=f"{i:04d}", uid=i)
    if peer == "2dgs":
        return Camera(**common, image=torch.zeros(3, H, W), gt_alpha_mask=None)
    # pgsr_dpsr's Camera takes gt_alpha_mask; the earlier PGSR commit's does not
    extra = {"gt_alpha_mask": None} if "gt_alpha_mask" in inspect.signature(Camera.__init__).parameters else {}
    return Camera(**common, image_width=W, image_height=H, image_path=os.path.join(exch, "images", f"{i:04d}.png"),
                  preload_img=False, data_device="cuda", **extra)


def main() -> None:
    peer, model, it, exch, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
    if peer not in ("2dgs", "pgsr"):
        sys.exit(f"peer must be '2dgs' or 'pgsr', got {peer!r}")
    meta = read_json(os.path.join(exch, "meta.json"))
    cams = np.load(os.path.join(exch, "cameras.npz"))
    g = GaussianModel(3)
    g.load_ply(os.path.join(model, "point_cloud", f"iteration_{it}", "point_cloud.ply"))
    pipe = SimpleNamespace(convert_SHs_python=False, compute_cov3D_python=False, depth_ratio=1.0, debug=False)
    kw = {} if peer == "2dgs" else {"app_model": None, "return_plane": False, "return_depth_normal": False}
    bg = torch.tensor(meta["background"] or [0.0, 0.0, 0.0], dtype=torch.float32, device="cuda")
    W, H = meta["width"], meta["height"]
    rgb = []
    with torch.no_grad():
        for i in meta["test"]:
            cam = _camera(peer, i, cams["K"][i], cams["w2c"][i], W, H, exch)
            rgb.append(render(cam, g, pipe, bg, **kw)["render"].clamp(0, 1).permute(1, 2, 0).cpu().numpy())
    np.savez(out, rgb=np.stack(rgb).astype(np.float16), n=len(g.get_xyz),
             peak=torch.cuda.max_memory_allocated())


if __name__ == "__main__":
    main()
