# SPDX-License-Identifier: Apache-2.0
"""Run inside a 2DGS checkout: render a trained model in the exchange folder's held-out views.

python _2dgs_views.py MODEL ITERATION EXCH OUT.npz
"""

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


def main() -> None:
    model, it, exch, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
    meta = read_json(os.path.join(exch, "meta.json"))
    cams = np.load(os.path.join(exch, "cameras.npz"))
    g = GaussianModel(3)
    g.load_ply(os.path.join(model, "point_cloud", f"iteration_{it}", "point_cloud.ply"))
    pipe = SimpleNamespace(convert_SHs_python=False, compute_cov3D_python=False, depth_ratio=1.0, debug=False)
    bg = torch.tensor(meta["background"] or [0.0, 0.0, 0.0], dtype=torch.float32, device="cuda")
    W, H = meta["width"], meta["height"]
    rgb = []
    with torch.no_grad():
        for i in meta["test"]:
            K, w2c = cams["K"][i], cams["w2c"][i]
            fovx, fovy = 2 * math.atan(W / (2 * K[0, 0])), 2 * math.atan(H / (2 * K[1, 1]))
            cam = Camera(colmap_id=i, R=w2c[:3, :3].T, T=w2c[:3, 3], FoVx=fovx, FoVy=fovy,
                         image=torch.zeros(3, H, W), gt_alpha_mask=None, image_name=f"{i:04d}", uid=i)
            rgb.append(render(cam, g, pipe, bg)["render"].clamp(0, 1).permute(1, 2, 0).cpu().numpy())
    np.savez(out, rgb=np.stack(rgb).astype(np.float16), n=len(g.get_xyz),
             peak=torch.cuda.max_memory_allocated())


if __name__ == "__main__":
    main()
