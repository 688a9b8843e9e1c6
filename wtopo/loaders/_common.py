# SPDX-License-Identifier: Apache-2.0
"""Helpers shared by the dataset readers: image decoding, alpha compositing, camera construction
with the camera index in error messages (and the principal-point sanity check every format gets),
OpenGL -> OpenCV axes, frames skipped for missing images, and on-the-fly downscaling."""

from __future__ import annotations

import json
import math
import os
import struct
import warnings

import numpy as np
import torch

from ..camera import Camera

__all__ = ["read_image", "read_json", "require_key", "parse_background", "make_camera", "opengl_c2w_to_w2c",
           "opencv_c2w_from_w2c_gl", "ImageStack", "find_file", "MIN_IMAGES_AFTER_SKIPPING",
           "PRINCIPAL_POINT_MARGIN"]

_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}

MIN_IMAGES_AFTER_SKIPPING = 2
"""Frames whose image file is missing are skipped; if fewer than this many images remain the load
fails instead: one view constrains no depth, so a fit on it is never what the user meant."""

PRINCIPAL_POINT_MARGIN = 0.5
"""How far outside its image a camera's principal point may lie, as a fraction of the image width
(for ``cx``) and height (for ``cy``): ``cx`` must lie in ``[-0.5 W, 1.5 W]``. Calibrated lenses put
it within a few percent of the centre and off-centre crops move it towards or just past an edge;
intrinsics stored for ``s`` times the image resolution put it at ``s / 2`` of the size, so this
catches ``s > 3`` (e.g. DTU's 1600 px intrinsics with 400 px images). Intrinsics for twice the
resolution put it at the image corner and pass; the formats that store the calibrated size
(COLMAP, nerfstudio ``w``/``h``) catch those by the size check."""

_MAX_NAMED_SKIPPED = 20  # a warning names at most this many skipped files (then "and N more"): one readable line

# what PIL raises for a corrupt, truncated or unsupported file (SyntaxError: "broken PNG file",
# struct.error: short header fields, EOFError: truncated frame data)
_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error)


def read_image(path: str) -> np.ndarray:
    """Decode an image file into float32 [H, W, C] in [0, 1] (C = 3, or 4 with alpha; grey -> RGB).

    Raises:
        FileNotFoundError: ``path`` is not a file.
        ValueError: the file cannot be decoded (not an image, corrupt, truncated), naming ``path``.
    """
    from PIL import Image

    if not os.path.isfile(path):
        raise FileNotFoundError(f"image file not found: {path}")
    try:
        with Image.open(path) as im:
            im.load()  # decode the pixels here: PIL reports a truncated file only when they are read
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I"):
                a = np.asarray(im, dtype=np.float32) / 65535.0
            else:
                if mode not in ("RGB", "RGBA"):
                    im = im.convert("RGBA" if ("A" in mode or "transparency" in im.info) else "RGB")
                a = np.asarray(im, dtype=np.float32) / 255.0
    except (*_DECODE_ERRORS, Image.DecompressionBombError) as e:
        raise ValueError(f"cannot read image {path}: {e}") from e
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


def read_json(path: str):
    """Parse a JSON file; a syntax error becomes a ValueError naming ``path``."""
    with open(path) as fh:
        try:
            return json.load(fh)
        except ValueError as e:
            raise ValueError(f"{path} is not valid JSON: {e}") from None


def require_key(record: dict, key: str, index: int, source: str):
    """``record[key]`` of frame ``index`` of ``source``; a missing key is a ValueError naming both."""
    if not isinstance(record, dict):
        raise ValueError(f"{source}: frame {index} must be a JSON object, got {type(record).__name__}")
    if key not in record:
        raise ValueError(f"{source}: frame {index} has no {key!r}")
    return record[key]


def make_camera(index: int, name: str, K, w2c, width: int, height: int, distortion=None, *,
                source: str) -> Camera:
    """Build a :class:`Camera`, re-raising validation errors with the camera index, name and file.

    Args:
        index: the camera's index in the scene, for messages.
        name: its image name, for messages and ``Camera.name``.
        K: intrinsics [3, 3] in pixels, float64.
        w2c: world-to-camera [4, 4] (OpenCV axes), float64.
        width: image width in pixels.
        height: image height in pixels.
        distortion: OpenCV ``k1 k2 p1 p2 (k3)`` or ``None``.
        source: the file the intrinsics were read from, for messages.

    Raises:
        ValueError: the camera is invalid, or its principal point lies more than
            :data:`PRINCIPAL_POINT_MARGIN` of the image size outside the image (intrinsics stored for
            another resolution).
    """
    try:
        cam = Camera(K, w2c, width, height, distortion, name)
    except (ValueError, TypeError) as e:
        raise ValueError(f"camera {index} ({name!r}) in {source}: {e}") from None
    cx, cy = float(cam.K[0, 2]), float(cam.K[1, 2])
    m = PRINCIPAL_POINT_MARGIN
    lo_x, hi_x, lo_y, hi_y = -m * width, (1 + m) * width, -m * height, (1 + m) * height
    if not (lo_x <= cx <= hi_x and lo_y <= cy <= hi_y):
        raise ValueError(
            f"camera {index} ({name!r}) in {source}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies far outside "
            f"its {width}x{height} (WxH) image (cx must be in [{lo_x:g}, {hi_x:g}], cy in [{lo_y:g}, {hi_y:g}]); "
            "the intrinsics may be for another image resolution: scale fx, fy, cx, cy by the image size over the "
            "size they were calibrated at")
    return cam


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
    output resolution), and the frames skipped because their image file is missing.

    Args:
        downscale: image size divisor (>= 1).
        background: colour RGBA images are composited onto (3 floats in [0, 1]) or ``None`` (black).
        source: the file that lists the frames (``transforms.json``, ``images.txt``, ...), for messages.
    """

    def __init__(self, downscale: float, background, *, source: str):
        f = float(downscale)
        if not math.isfinite(f) or f < 1:
            raise ValueError(f"downscale must be a finite number >= 1, got {downscale!r}")
        self.factor = f
        self.background = background
        self.source = source
        self.images, self.masks, self.cameras = [], [], []
        self.skipped: list[str] = []

    def skip(self, name: str) -> None:
        """Record a frame whose image file ``name`` is missing; :meth:`arrays` warns once for all of them."""
        self.skipped.append(name)

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
        """(cameras, images [N, H, W, 3], masks [N, H, W] or None); masks only when every image has one.

        Warns once (``UserWarning``, count first, the files named) when frames were skipped.

        Raises:
            ValueError: no images, or fewer than :data:`MIN_IMAGES_AFTER_SKIPPING` left after skipping.
        """
        n_skip, n_left = len(self.skipped), len(self.images)
        if n_skip:
            named = ", ".join(self.skipped[:_MAX_NAMED_SKIPPED])
            if n_skip > _MAX_NAMED_SKIPPED:
                named += f" and {n_skip - _MAX_NAMED_SKIPPED} more"
            what = f"{n_skip} of {n_skip + n_left} images listed in {self.source} are missing"
            if n_left < MIN_IMAGES_AFTER_SKIPPING:
                raise ValueError(f"{what} ({named}); {n_left} left, at least {MIN_IMAGES_AFTER_SKIPPING} are needed")
            warnings.warn(f"{what} and were skipped: {named}", UserWarning, stacklevel=3)
        if not self.images:
            raise ValueError(f"{self.source} lists no images")
        sizes = {im.shape[:2] for im in self.images}
        if len(sizes) > 1:
            raise ValueError(f"all images must share one size, got sizes (HxW) {sorted(sizes)}; resize them first")
        masks = np.stack(self.masks) if all(m is not None for m in self.masks) else None
        return self.cameras, np.stack(self.images), masks
