# SPDX-License-Identifier: Apache-2.0
"""nerfstudio ``transforms.json``: OpenGL camera axes, intrinsics ``fl_x fl_y cx cy w h`` shared at
the top level or given per frame, OpenCV distortion ``k1 k2 p1 p2 (k3)``, optional ``mask_path``,
``ply_file_path`` (init points) and ``train_filenames`` / ``test_filenames``
(nerfstudio ``nerfstudio_dataparser.py``). The poses are taken as written: the scene's world is the
file's frame (nerfstudio's own auto-orientation and scaling are not applied)."""

from __future__ import annotations

import json
import os

import numpy as np

from ._common import ImageStack, make_camera, opengl_c2w_to_w2c, parse_background, read_image, read_mask

__all__ = ["load_nerfstudio"]

_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def load_nerfstudio(path: str, *, background=None, downscale: float = 1):
    """Read a nerfstudio dataset (folder holding ``transforms.json``, or the file itself).

    Args:
        path: dataset folder or ``transforms.json``.
        background: colour RGBA images are composited onto (default white when they have alpha).
        downscale: image size divisor (>= 1).

    Raises:
        ValueError: a camera model other than SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or
            OPENCV (e.g. OPENCV_FISHEYE, EQUIRECTANGULAR); missing intrinsics; a bad pose.
    """
    from ..scene import Scene

    fp = path if os.path.isfile(path) else os.path.join(path, "transforms.json")
    root = os.path.dirname(fp)
    with open(fp) as fh:
        meta = json.load(fh)
    bg = parse_background(background)
    stack = ImageStack(downscale, bg if bg is not None else (1.0, 1.0, 1.0))
    any_alpha = False
    names = []
    for i, fr in enumerate(meta.get("frames", [])):
        def get(k, default=None):
            return fr.get(k, meta.get(k, default))

        model = get("camera_model", "OPENCV")
        if model not in _SUPPORTED:
            raise ValueError(f"camera {i} ({fr.get('file_path')!r}): camera_model {model} is not supported; wtopo "
                             f"reads {', '.join(_SUPPORTED)}. Undistort the images first (e.g. `colmap "
                             "image_undistorter` or `ns-process-data` with a pinhole model)")
        if get("k4", 0.0):
            raise ValueError(f"camera {i} ({fr.get('file_path')!r}): k4 = {get('k4')} is a fisheye coefficient; "
                             "wtopo reads OpenCV k1 k2 p1 p2 k3 only")
        ip = os.path.normpath(os.path.join(root, fr["file_path"]))
        img = read_image(ip)
        any_alpha |= img.shape[-1] == 4
        h, w = img.shape[:2]
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None:
            raise ValueError(f"camera {i} ({fr['file_path']!r}): no fl_x in the frame or at the top level")
        fy = fx if fy is None else fy
        W, H = int(get("w", w)), int(get("h", h))
        if (W, H) != (w, h):
            raise ValueError(f"camera {i} ({fr['file_path']!r}): size {W}x{H} (WxH) does not match its image's {w}x{h}")
        K = np.array([[float(fx), 0, float(get("cx", 0.5 * w))], [0, float(fy), float(get("cy", 0.5 * h))], [0, 0, 1.0]])
        d = [float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
        cam = make_camera(i, fr["file_path"], K, opengl_c2w_to_w2c(fr["transform_matrix"]), w, h, d)
        mask = read_mask(os.path.join(root, fr["mask_path"])) if "mask_path" in fr else None
        stack.add(cam, img, mask)
        names.append(fr["file_path"])
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
    return Scene(cameras, images, masks=masks, points=points, point_colors=colors,
                 background=stack.background if any_alpha else bg,
                 name=os.path.basename(os.path.normpath(root)),
                 train_indices=indices("train_filenames"), test_indices=indices("test_filenames"))
