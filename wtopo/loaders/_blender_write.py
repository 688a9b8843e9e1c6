# SPDX-License-Identifier: Apache-2.0
"""Writing a scene as a Blender / NeRF-synthetic dataset (:meth:`wtopo.Scene.save`,
:func:`wtopo.loaders.write_blender`); :mod:`wtopo.loaders.blender` reads it back.

It takes the scene by its attributes and never imports :mod:`wtopo.scene`, so the scene can call it.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from ._common import opencv_c2w_from_w2c_gl

__all__ = ["write_blender"]


def _frame(camera, file_path: str) -> dict:
    K = camera.K
    fr = {
        "file_path": file_path,
        "rotation": 0.0,
        "transform_matrix": opencv_c2w_from_w2c_gl(camera).tolist(),
        "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "w": camera.width, "h": camera.height,
    }
    if K[0, 1] != 0:
        fr["skew"] = float(K[0, 1])
    if camera.distortion is not None:
        fr.update({k: float(v) for k, v in zip(("k1", "k2", "p1", "p2", "k3"), camera.distortion)})
    return fr


def write_blender(scene, path: str) -> None:
    """Write ``scene`` as a Blender / NeRF-synthetic dataset (see :meth:`wtopo.Scene.save`).

    Images are 8-bit RGBA PNGs (alpha = mask; RGB when the scene has no masks) under ``train/``, ``test/`` (and
    ``val/`` for images in neither split); ``gt_mesh.ply`` holds the ground-truth mesh.
    """
    from PIL import Image

    os.makedirs(path, exist_ok=True)
    n = len(scene)
    if scene.train_indices is None and scene.test_indices is None:
        groups = {"train": list(range(n)), "test": []}
    else:
        train = [] if scene.train_indices is None else [int(i) for i in scene.train_indices]
        test = [] if scene.test_indices is None else [int(i) for i in scene.test_indices]
        rest = sorted(set(range(n)) - set(train) - set(test))
        groups = {"train": train, "test": test}
        if rest:
            groups["val"] = rest
    images = (scene.images.detach().cpu().numpy() * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
    masks = None if scene.masks is None else scene.masks.detach().cpu().numpy()
    cam0 = scene.cameras[0]
    for split, idx in groups.items():
        os.makedirs(os.path.join(path, split), exist_ok=True)
        frames = []
        for k, i in enumerate(idx):
            rel = f"{split}/r_{k}"
            if masks is None:  # no alpha channel: the loader must not invent an all-true mask
                im = Image.fromarray(images[i], "RGB")
            else:
                im = Image.fromarray(np.concatenate([images[i], masks[i].astype(np.uint8)[..., None] * 255], axis=-1),
                                     "RGBA")
            im.save(os.path.join(path, rel + ".png"))
            frames.append(_frame(scene.cameras[i], "./" + rel))
        meta = {
            "camera_angle_x": 2.0 * math.atan(0.5 * cam0.width / cam0.K[0, 0]),
            "name": scene.name,
            "background": None if scene.background is None else list(scene.background),
            "frames": frames,
        }
        if scene.bounds is not None:
            meta["bounds"] = [scene.bounds[0].tolist(), scene.bounds[1].tolist()]
        with open(os.path.join(path, f"transforms_{split}.json"), "w") as fh:
            json.dump(meta, fh, indent=1)
    if scene.gt_mesh is not None:
        scene.gt_mesh.export(os.path.join(path, "gt_mesh.ply"))
