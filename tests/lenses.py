# SPDX-License-Identifier: Apache-2.0
"""A scene seen through a barrel lens: the distorted twin of a pinhole rig, for tests of every
depth projection that must honour the camera's own lens."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from wtopo.camera import Camera

BARREL = (-0.3, 0.05, 0.002, -0.002, 0.0)  # ~3 px at the corners of 64 x 48 px


def barrel_twin(scene) -> tuple[list[Camera], torch.Tensor]:
    """The scene's cameras with a :data:`BARREL` lens of the same pose and their images resampled
    from the pinhole ones (what that lens would have photographed): ``(cameras, images [V, H, W, 3])``."""
    cams, imgs = [], []
    for cam, img in zip(scene.cameras, scene.images):
        lens = Camera(cam.K, cam.world_to_camera, cam.width, cam.height, np.array(BARREL), cam.name)
        o, d = lens.pixel_rays()
        uv, _ = cam.project((o + 3.0 * d).reshape(-1, 3).numpy())
        g = torch.as_tensor(np.stack([uv[:, 0] / cam.width * 2 - 1, uv[:, 1] / cam.height * 2 - 1], -1),
                            dtype=torch.float32).reshape(1, cam.height, cam.width, 2)
        imgs.append(F.grid_sample(img.permute(2, 0, 1)[None], g, align_corners=False)[0].permute(1, 2, 0))
        cams.append(lens)
    return cams, torch.stack(imgs)
