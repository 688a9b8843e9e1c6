# SPDX-License-Identifier: Apache-2.0
"""Blender / NeRF-synthetic datasets: ``transforms_{train,val,test}.json`` + PNG images.

Reading follows bmild/nerf ``load_blender.py`` and 3DGS ``readCamerasFromTransforms``:
``transform_matrix`` is camera-to-world in OpenGL axes, ``fx = fy = W / (2 tan(camera_angle_x / 2))``,
principal point at the image centre, RGBA composited onto a white or black background (alpha
becomes the mask). Per-frame or top-level ``fl_x, fl_y, cx, cy`` (and ``k1 k2 p1 p2 k3``) override
that, which is how :func:`write_blender` stores general cameras.
"""

from __future__ import annotations

import math
import os

import numpy as np

from ._blender_write import write_blender
from ._common import (
    ImageStack,
    make_camera,
    opengl_c2w_to_w2c,
    parse_background,
    read_image,
    read_json,
    require_key,
)

__all__ = ["load_blender", "write_blender"]

_SPLITS = ("train", "val", "test")


def _intrinsics(meta: dict, frame: dict, w: int, h: int):
    def get(k):
        return frame.get(k, meta.get(k))

    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        ax = get("camera_angle_x")
        if ax is None:
            raise ValueError("transforms file gives neither camera_angle_x nor fl_x")
        fx = 0.5 * w / math.tan(0.5 * float(ax))
    if fy is None:
        ay = get("camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * float(ay)) if ay is not None else fx
    cx, cy = get("cx"), get("cy")
    cx = 0.5 * w if cx is None else float(cx)
    cy = 0.5 * h if cy is None else float(cy)
    K = np.array([[float(fx), float(get("skew") or 0.0), cx], [0, float(fy), cy], [0, 0, 1.0]])
    d = [float(get(k) or 0.0) for k in ("k1", "k2", "p1", "p2", "k3")]
    return K, (d if any(d) else None)


def _image_path(root: str, file_path: str) -> str | None:
    """The image file of ``file_path`` (written without extension by NeRF-synthetic), or ``None``."""
    p = os.path.normpath(os.path.join(root, file_path))
    if os.path.splitext(p)[1].lower() in (".png", ".jpg", ".jpeg") and os.path.isfile(p):
        return p
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
        if os.path.isfile(p + ext):
            return p + ext
    return None


def load_blender(path: str, *, splits=("train", "test"), background=None, downscale: float = 1):
    """Read a Blender / NeRF-synthetic dataset directory.

    Args:
        path: directory holding ``transforms_<split>.json``.
        splits: which of ``train``, ``val``, ``test`` to read (missing files are skipped); frames
            come in this order and ``train`` / ``test`` become the scene's split indices.
        background: ``"white"``, ``"black"``, 3 floats or ``None`` (the file's ``background`` key
            when written by :func:`write_blender`, else white as in NeRF).
        downscale: image size divisor (>= 1).

    Frames whose image file is missing (tried as written, then with ``.png`` / ``.jpg``) are
    skipped with one warning naming them.

    Returns:
        :class:`wtopo.Scene` in the dataset's world frame.

    Raises:
        ValueError: bad intrinsics or pose (naming the camera and file), a principal point far
            outside the image, an unreadable image, fewer than
            :data:`~wtopo.loaders._common.MIN_IMAGES_AFTER_SKIPPING` images left after skipping.
    """
    from ..scene import Scene

    for s in splits:
        if s not in _SPLITS:
            raise ValueError(f"splits must be a subset of {_SPLITS}, got {splits!r}")
    metas = {}
    for s in splits:
        p = os.path.join(path, f"transforms_{s}.json")
        if os.path.isfile(p):
            metas[s] = read_json(p)
            if not isinstance(metas[s], dict):
                raise ValueError(f"{p} must hold a JSON object, got {type(metas[s]).__name__}")
    if not metas:
        raise FileNotFoundError(f"no transforms_{{{','.join(splits)}}}.json in {path}")
    first = next(iter(metas.values()))
    bg = parse_background(background, None)
    if bg is None:
        bg = parse_background(first.get("background", "white")) if "background" in first else (1.0, 1.0, 1.0)
    files = [f"transforms_{s}.json" for s in metas]
    stack = ImageStack(downscale, bg, source=os.path.join(path, files[0] if len(files) == 1 else
                                                          f"transforms_{{{','.join(metas)}}}.json"))
    index = {}
    any_alpha = False
    for s, meta in metas.items():
        index[s] = []
        source = os.path.join(path, f"transforms_{s}.json")
        for k, frame in enumerate(meta.get("frames", [])):
            file_path = require_key(frame, "file_path", k, source)
            ip = _image_path(path, file_path)
            if ip is None:
                stack.skip(file_path)
                continue
            img = read_image(ip)
            any_alpha |= img.shape[-1] == 4
            h, w = img.shape[:2]
            i = len(stack.cameras)
            name = os.path.relpath(ip, path)
            try:
                K, dist = _intrinsics(meta, frame, w, h)
            except (TypeError, ValueError) as e:
                raise ValueError(f"camera {i} ({name!r}) in {source}: {e}") from None
            w2c = opengl_c2w_to_w2c(require_key(frame, "transform_matrix", k, source))
            cam = make_camera(i, name, K, w2c, w, h, dist, source=source)
            index[s].append(i)
            stack.add(cam, img)
    cams, images, masks = stack.arrays()
    train = np.asarray(index.get("train", []), dtype=np.int64)
    test = np.asarray(index.get("test", []), dtype=np.int64)
    if len(test) == 0:
        train = test = None
    bounds = first.get("bounds")
    gt = None
    mesh_path = os.path.join(path, "gt_mesh.ply")
    if os.path.isfile(mesh_path):
        import trimesh

        gt = trimesh.load(mesh_path, process=False, force="mesh")
    return Scene(cams, images, masks=masks, background=bg if any_alpha or "background" in first else None,
                 bounds=None if bounds is None else (bounds[0], bounds[1]), gt_mesh=gt,
                 name=first.get("name", os.path.basename(os.path.normpath(path))),
                 train_indices=train, test_indices=test)
