# SPDX-License-Identifier: Apache-2.0
"""Helpers shared by the dataset readers: image decoding, alpha compositing, camera construction
with the camera index in error messages, OpenGL -> OpenCV axes, and on-the-fly downscaling."""

from __future__ import annotations

import math
import os

import numpy as np
import torch

from ..camera import Camera

__all__ = ["read_image", "parse_background", "make_camera", "opengl_c2w_to_w2c", "opencv_c2w_from_w2c_gl",
           "ImageStack", "find_file"]

_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def read_image(path: str) -> np.ndarray:
    """Decode an image file into float32 [H, W, C] in [0, 1] (C = 3, or 4 with alpha; grey -> RGB)."""
    from PIL import Image

    if not os.path.isfile(path):
        raise FileNotFoundError(f"image file not found: {path}")
    with Image.open(path) as im:
        mode = im.mode
        if mode in ("I;16", "I;16B", "I;16L", "I"):
            a = np.asarray(im, dtype=np.float32) / 65535.0
        else:
            if mode not in ("RGB", "RGBA"):
                im = im.convert("RGBA" if ("A" in mode or "transparency" in im.info) else "RGB")
            a = np.asarray(im, dtype=np.float32) / 255.0
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return a


def read_mask(path: str) -> np.ndarray:
    """Decode a mask image into bool [H, W] (first channel > 0.5, or alpha when present)."""
    a = read_image(path)
    return (a[..., 3] if a.shape[-1] == 4 else a[..., 0]) > 0.5


def parse_background(background, default=None):
    """``"white"``, ``"black"``, 3 floats in [0, 1] or ``None`` -> tuple or None."""
    if background is None:
        return default
    if isinstance(background, str):
        if background not in _BACKGROUNDS:
            raise ValueError(f"background must be 'white', 'black', 3 floats or None, got {background!r}")
        return _BACKGROUNDS[background]
    b = np.asarray(background, dtype=np.float64).reshape(-1)
    if b.shape != (3,) or not np.all((b >= 0) & (b <= 1)):
        raise ValueError(f"background must be 'white', 'black', 3 floats in [0, 1] or None, got {background!r}")
    return tuple(float(v) for v in b)


def make_camera(index: int, name: str, K, w2c, width: int, height: int, distortion=None) -> Camera:
    """Build a :class:`Camera`, re-raising validation errors with the camera index and name."""
    try:
        return Camera(K, w2c, width, height, distortion, name)
    except (ValueError, TypeError) as e:
        raise ValueError(f"camera {index} ({name!r}): {e}") from None


def opengl_c2w_to_w2c(c2w) -> np.ndarray:
    """Camera-to-world in OpenGL/Blender axes (+y up, looking down -z), [3, 4] or [4, 4], to an
    OpenCV world-to-camera [4, 4] (float64)."""
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape not in ((3, 4), (4, 4)):
        raise ValueError(f"transform_matrix must be 3x4 or 4x4, got shape {list(m.shape)}")
    c = np.eye(4)
    c[:3, :4] = m[:3, :4]
    c[:3, 1:3] *= -1  # OpenGL (y up, z back) -> OpenCV (y down, z forward)
    R = c[:3, :3]
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ c[:3, 3]
    return w2c


def opencv_c2w_from_w2c_gl(camera: Camera) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_w2c`: the OpenGL camera-to-world [4, 4] of ``camera``."""
    c2w = camera.camera_to_world
    c2w[:3, 1:3] *= -1
    return c2w


def find_file(root: str, names) -> str | None:
    """First of ``names`` that exists under ``root``."""
    for n in names:
        p = os.path.join(root, n)
        if os.path.exists(p):
            return p
    return None


class ImageStack:
    """Accumulates images / masks of one size, downscaling each as it arrives (keeps memory at the
    output resolution)."""

    def __init__(self, downscale: float, background):
        f = float(downscale)
        if not math.isfinite(f) or f < 1:
            raise ValueError(f"downscale must be a finite number >= 1, got {downscale!r}")
        self.factor = f
        self.background = background
        self.images, self.masks, self.cameras = [], [], []
        self.alpha_seen = False

    def _resize(self, a: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
        t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
        t = t[None, None] if t.ndim == 2 else t.permute(2, 0, 1)[None]
        t = torch.nn.functional.interpolate(t, size=(h, w), mode=mode)
        return t[0, 0].numpy() if a.ndim == 2 else t[0].permute(1, 2, 0).numpy()

    def add(self, camera: Camera, rgba: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Add one image (float [H, W, 3|4]); RGBA is composited onto the background and its alpha
        becomes the mask unless ``mask`` is given."""
        i = len(self.cameras)
        h, w = rgba.shape[:2]
        if (camera.width, camera.height) != (w, h):
            raise ValueError(f"camera {i} ({camera.name!r}): size {camera.width}x{camera.height} (WxH) does not "
                             f"match its image's {w}x{h}")
        if mask is not None and mask.shape != (h, w):
            raise ValueError(f"camera {i} ({camera.name!r}): mask size {mask.shape[1]}x{mask.shape[0]} does not "
                             f"match its image's {w}x{h}")
        rgb = rgba[..., :3]
        if rgba.shape[-1] == 4:
            a = rgba[..., 3:4]
            bg = np.asarray(self.background if self.background is not None else (0.0, 0.0, 0.0), dtype=np.float32)
            rgb = rgb * a + bg * (1 - a)
            if mask is None:
                mask = a[..., 0] > 0.5
        if self.factor != 1:
            camera = camera.scaled(1.0 / self.factor)
            rgb = self._resize(rgb, camera.height, camera.width, "area")
            if mask is not None:
                mask = self._resize(mask.astype(np.float32), camera.height, camera.width, "area") >= 0.5
        self.cameras.append(camera)
        self.images.append(np.clip(rgb, 0, 1).astype(np.float32))
        self.masks.append(mask)

    def arrays(self):
        """(cameras, images [N, H, W, 3], masks [N, H, W] or None); masks only when every image has one."""
        if not self.images:
            raise ValueError("the dataset lists no images")
        sizes = {im.shape[:2] for im in self.images}
        if len(sizes) > 1:
            raise ValueError(f"all images must share one size, got sizes (HxW) {sorted(sizes)}; resize them first")
        masks = np.stack(self.masks) if all(m is not None for m in self.masks) else None
        return self.cameras, np.stack(self.images), masks
