# SPDX-License-Identifier: Apache-2.0
"""nerfstudio ``transforms.json``: OpenGL camera axes, intrinsics ``fl_x fl_y cx cy w h`` shared at
the top level or given per frame, OpenCV distortion ``k1 k2 p1 p2 (k3)``, optional ``mask_path``,
``ply_file_path`` (init points) and ``train_filenames`` / ``test_filenames``
(nerfstudio ``nerfstudio_dataparser.py``). The poses are taken as written: the scene's world is the
file's frame (nerfstudio's own auto-orientation and scaling are not applied)."""

from __future__ import annotations

import os

import numpy as np

from ._common import (
    ImageStack,
    make_camera,
    opengl_c2w_to_w2c,
    parse_background,
    read_image,
    read_json,
    read_mask,
    require_key,
)

__all__ = ["load_nerfstudio"]

_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def load_nerfstudio(path: str, *, background=None, downscale: float = 1):
    """Read a nerfstudio dataset (folder holding ``transforms.json``, or the file itself).

    Args:
        path: dataset folder or ``transforms.json``.
        background: colour RGBA images are composited onto (default white when they have alpha).
        downscale: image size divisor (>= 1).

    A top-level ``aabb`` (``[[min], [max]]``, world frame) becomes ``Scene.bounds``, the fit's region
    of interest; ``aabb_scale`` is kept in ``Scene.info``. Frames whose image file is missing are
    skipped with one warning naming them.

    Raises:
        ValueError: a camera model other than SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or
            OPENCV (e.g. OPENCV_FISHEYE, EQUIRECTANGULAR); missing intrinsics; a bad pose; a
            principal point far outside the image; an unreadable image; fewer than
            :data:`~wtopo.loaders._common.MIN_IMAGES_AFTER_SKIPPING` images left after skipping.
    """
    from ..scene import Scene

    fp = path if os.path.isfile(path) else os.path.join(path, "transforms.json")
    root = os.path.dirname(fp)
    meta = read_json(fp)
    if not isinstance(meta, dict):
        raise ValueError(f"{fp} must hold a JSON object, got {type(meta).__name__}")
    bg = parse_background(background)
    stack = ImageStack(downscale, bg if bg is not None else (1.0, 1.0, 1.0), source=fp)
    any_alpha = False
    names = []
    for k, fr in enumerate(meta.get("frames", [])):
        file_path = require_key(fr, "file_path", k, fp)
        ip = os.path.normpath(os.path.join(root, file_path))
        if not os.path.isfile(ip):
            stack.skip(file_path)
            continue
        i = len(stack.cameras)  # the camera's index in the scene

        def get(key, default=None, fr=fr):  # a frame's own value overrides the top level's
            return fr.get(key, meta.get(key, default))

        model = get("camera_model", "OPENCV")
        if model not in _SUPPORTED:
            raise ValueError(f"camera {i} ({file_path!r}) in {fp}: camera_model {model} is not supported; wtopo "
                             f"reads {', '.join(_SUPPORTED)}. Undistort the images first (e.g. `colmap "
                             "image_undistorter` or `ns-process-data` with a pinhole model)")
        if get("k4", 0.0):
            raise ValueError(f"camera {i} ({file_path!r}) in {fp}: k4 = {get('k4')} is a fisheye coefficient; "
                             "wtopo reads OpenCV k1 k2 p1 p2 k3 only")
        img = read_image(ip)
        any_alpha |= img.shape[-1] == 4
        h, w = img.shape[:2]
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None:
            raise ValueError(f"camera {i} ({file_path!r}) in {fp}: no fl_x in the frame or at the top level")
        fy = fx if fy is None else fy
        size = int(get("w", w)), int(get("h", h))
        if size != (w, h):
            raise ValueError(f"camera {i} ({file_path!r}) in {fp}: size {size[0]}x{size[1]} (WxH) does not match its "
                             f"image's {w}x{h}; the intrinsics may be for another image resolution")
        cx, cy = float(get("cx", 0.5 * w)), float(get("cy", 0.5 * h))
        K = np.array([[float(fx), 0, cx], [0, float(fy), cy], [0, 0, 1.0]])
        d = [float(get(key, 0.0)) for key in ("k1", "k2", "p1", "p2", "k3")]
        w2c = opengl_c2w_to_w2c(require_key(fr, "transform_matrix", k, fp))
        cam = make_camera(i, file_path, K, w2c, w, h, d, source=fp)
        mask = read_mask(os.path.join(root, fr["mask_path"])) if "mask_path" in fr else None
        stack.add(cam, img, mask)
        names.append(file_path)
    cameras, images, masks = stack.arrays()

    def indices(key):
        if key not in meta:
            return None
        want = {os.path.normpath(f) for f in meta[key]}
        return np.array([k for k, n in enumerate(names) if os.path.normpath(n) in want], dtype=np.int64)

    points = colors = None
    if "ply_file_path" in meta:
        import trimesh

        pc = trimesh.load(os.path.join(root, meta["ply_file_path"]), process=False)
        points = np.asarray(pc.vertices, dtype=np.float64)
        cols = getattr(getattr(pc, "visual", None), "vertex_colors", None)
        if cols is not None and len(cols) == len(points):
            colors = np.asarray(cols, dtype=np.float64)[:, :3] / 255.0
    bounds = None
    if "aabb" in meta:  # instant-ngp / nerfstudio region of interest, world frame (the fit's ROI)
        box = np.asarray(meta["aabb"], dtype=np.float64)
        if box.shape != (2, 3) or not np.all(np.isfinite(box)) or not np.all(box[1] > box[0]):
            raise ValueError(f"aabb in {fp} must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, "
                             f"got {meta['aabb']!r}")
        bounds = (box[0], box[1])
    info = {"aabb_scale": float(meta["aabb_scale"])} if "aabb_scale" in meta else {}
    return Scene(cameras, images, masks=masks, points=points, point_colors=colors,
                 background=stack.background if any_alpha else bg, bounds=bounds, info=info,
                 name=os.path.basename(os.path.normpath(root)),
                 train_indices=indices("train_filenames"), test_indices=indices("test_filenames"))
