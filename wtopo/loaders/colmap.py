# SPDX-License-Identifier: Apache-2.0
"""COLMAP sparse models (``sparse/0/{cameras,images,points3D}.{bin,txt}``) and their images.

Field layout from COLMAP ``doc/format.rst`` and ``scripts/python/read_write_model.py``: poses are
world-to-camera (Hamilton quaternion ``qw qx qy qz`` and ``t``), OpenCV camera axes, pixel centres
at +0.5 (wtopo's convention). Binary files are preferred over text when both exist.
"""

from __future__ import annotations

import os
import struct

import numpy as np

from ._common import ImageStack, make_camera, read_image, read_mask

__all__ = ["load_colmap", "find_colmap_model", "read_model", "qvec_to_rotmat", "CAMERA_MODELS"]

# id -> (name, number of parameters), read_write_model.py's table
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
_NAME_TO_ID = {v[0]: k for k, v in CAMERA_MODELS.items()}
_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def _unsupported(camera_id: int, model) -> ValueError:
    return ValueError(
        f"COLMAP camera {camera_id} uses camera model {model}; wtopo reads {', '.join(_SUPPORTED)}. "
        "Undistort the images first: `colmap image_undistorter --image_path <images> --input_path "
        "<sparse/0> --output_path <out>` and load <out>")


def qvec_to_rotmat(q) -> np.ndarray:
    """Rotation matrix [3, 3] of a Hamilton quaternion ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _intrinsics(camera_id: int, model: str, params) -> tuple[np.ndarray, list | None]:
    p = [float(v) for v in params]
    want = CAMERA_MODELS[_NAME_TO_ID[model]][1]
    if len(p) != want:
        raise ValueError(f"COLMAP camera {camera_id} ({model}) must have {want} parameters, got {len(p)}")
    if model == "SIMPLE_PINHOLE":
        (f, cx, cy), d = p, None
        fx = fy = f
    elif model == "PINHOLE":
        (fx, fy, cx, cy), d = p, None
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        d = [k, 0, 0, 0]
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        d = [k1, k2, 0, 0]
    else:  # OPENCV
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        d = [k1, k2, p1, p2]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), d


class _Reader:
    def __init__(self, path: str):
        with open(path, "rb") as fh:
            self.b = fh.read()
        self.o = 0
        self.path = path

    def read(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.o + size > len(self.b):
            raise ValueError(f"{self.path} is truncated at byte {self.o}")
        v = struct.unpack_from("<" + fmt, self.b, self.o)
        self.o += size
        return v

    def cstring(self) -> str:
        end = self.b.find(b"\x00", self.o)
        if end < 0:
            raise ValueError(f"{self.path} is truncated in an image name at byte {self.o}")
        s = self.b[self.o:end].decode("utf-8")
        self.o = end + 1
        return s


def _read_cameras_bin(path):
    r = _Reader(path)
    out = {}
    for _ in range(r.read("Q")[0]):
        cid, mid, w, h = r.read("iiQQ")
        if mid not in CAMERA_MODELS:
            raise _unsupported(cid, f"id {mid}")
        name, k = CAMERA_MODELS[mid]
        if name not in _SUPPORTED:
            raise _unsupported(cid, f"{name} (id {mid})")
        out[cid] = (name, int(w), int(h), r.read("d" * k))
    return out


def _read_cameras_txt(path):
    out = {}
    with open(path) as fh:
        for line in fh:
            t = line.split()
            if not t or t[0].startswith("#"):
                continue
            cid, model = int(t[0]), t[1]
            if model not in _SUPPORTED:
                raise _unsupported(cid, model)
            out[cid] = (model, int(t[2]), int(t[3]), [float(v) for v in t[4:]])
    return out


def _read_images_bin(path):
    r = _Reader(path)
    out = {}
    for _ in range(r.read("Q")[0]):
        iid = r.read("i")[0]
        q, t = r.read("dddd"), r.read("ddd")
        cid = r.read("i")[0]
        name = r.cstring()
        n2d = r.read("Q")[0]
        r.o += n2d * struct.calcsize("<ddq")
        out[iid] = (q, t, cid, name)
    return out


def _read_images_txt(path):
    out = {}
    with open(path) as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    # two lines per image; the second (2D points) may be empty
    for k in range(0, len(lines), 2):
        t = lines[k].split()
        if not t:
            continue
        iid = int(t[0])
        out[iid] = ([float(v) for v in t[1:5]], [float(v) for v in t[5:8]], int(t[8]), " ".join(t[9:]))
    return out


def _read_points_bin(path):
    r = _Reader(path)
    n = r.read("Q")[0]
    xyz, rgb = np.zeros((n, 3)), np.zeros((n, 3))
    for i in range(n):
        r.read("Q")
        xyz[i] = r.read("ddd")
        rgb[i] = r.read("BBB")
        r.read("d")
        track_len = r.read("Q")[0]
        r.o += track_len * struct.calcsize("<ii")
    return xyz, rgb / 255.0


def _read_points_txt(path):
    xyz, rgb = [], []
    with open(path) as fh:
        for line in fh:
            t = line.split()
            if not t or t[0].startswith("#"):
                continue
            xyz.append([float(v) for v in t[1:4]])
            rgb.append([float(v) for v in t[4:7]])
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3), np.asarray(rgb, dtype=np.float64).reshape(-1, 3) / 255.0


def find_colmap_model(path: str) -> str | None:
    """The folder holding ``cameras.{bin,txt}``: ``path``, ``path/sparse/0`` or ``path/sparse``."""
    for d in (path, os.path.join(path, "sparse", "0"), os.path.join(path, "sparse")):
        if any(os.path.isfile(os.path.join(d, f"cameras.{e}")) for e in ("bin", "txt")):
            return d
    return None


def _model_file(model_dir: str, stem: str) -> tuple[str | None, str | None]:
    """``(path, "bin" | "txt")`` of ``stem`` in a sparse model (binary first, as COLMAP reads), or ``(None, None)``."""
    for ext in ("bin", "txt"):
        p = os.path.join(model_dir, f"{stem}.{ext}")
        if os.path.isfile(p):
            return p, ext
    return None, None


def read_model(model_dir: str):
    """Read ``(cameras, images, points)`` of a sparse model: cameras ``{id: (model, w, h, params)}``,
    images ``{id: (qvec, tvec, camera_id, name)}``, points ``(xyz [P, 3], rgb [P, 3] in [0, 1])``
    or ``None`` when ``points3D`` is absent. Binary files first, text as fallback."""
    cp, ce = _model_file(model_dir, "cameras")
    ip, ie = _model_file(model_dir, "images")
    if cp is None or ip is None:
        raise FileNotFoundError(f"{model_dir} must hold cameras.bin/.txt and images.bin/.txt")
    cams = _read_cameras_bin(cp) if ce == "bin" else _read_cameras_txt(cp)
    imgs = _read_images_bin(ip) if ie == "bin" else _read_images_txt(ip)
    pp, pe = _model_file(model_dir, "points3D")
    pts = None if pp is None else (_read_points_bin(pp) if pe == "bin" else _read_points_txt(pp))
    return cams, imgs, pts


def _image_root(path: str, model_dir: str, first_name: str | None) -> str:
    workspace = os.path.dirname(os.path.dirname(model_dir))
    for d in (os.path.join(path, "images"), os.path.join(workspace, "images"),
              os.path.join(os.path.dirname(model_dir), "images"), os.path.join(workspace, "image")):
        if os.path.isdir(d):
            return d
    # a folder of photos that wtopo's structure from motion gave a model: photos/sparse/0 beside the images
    for d in (path, workspace):
        if first_name is not None and os.path.isfile(os.path.join(d, first_name)):
            return d
    raise FileNotFoundError(f"no images/ folder next to the COLMAP model in {path}")


def load_colmap(path: str, *, background=None, downscale: float = 1, images_dir: str | None = None):
    """Read a COLMAP workspace (``images/`` + ``sparse/0``), images sorted by name.

    Masks are read from ``masks/<name>`` or ``masks/<name>.png`` when present for every image; an
    RGBA image (a photo whose background a matting tool removed) is composited onto ``background``
    (black when ``None``) and its alpha is the mask unless a mask file is given (COLMAP itself ignores
    alpha).
    ``points3D`` become the scene's init points and colours.

    Args:
        path: workspace folder (or the model folder itself).
        background: constant background colour the images show, or ``None`` (real background).
        downscale: image size divisor (>= 1).
        images_dir: image folder, default ``<path>/images`` (or ``<path>`` itself when it holds the
            images beside ``sparse/``, as :func:`~wtopo.loaders.sfm.run_sfm` leaves a folder of photos).

    Images the model lists whose file is missing are skipped with one warning naming them.

    Raises:
        ValueError: a camera model other than SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or
            OPENCV (the message says how to undistort), a bad pose (names the image), a principal
            point far outside the image, an unreadable image, fewer than
            :data:`~wtopo.loaders._common.MIN_IMAGES_AFTER_SKIPPING` images left after skipping.
    """
    from ..scene import Scene
    from ._common import parse_background

    model_dir = find_colmap_model(path)
    if model_dir is None:
        raise FileNotFoundError(f"no COLMAP model (cameras.bin/.txt) in {path}, {path}/sparse/0 or {path}/sparse")
    cams, imgs, pts = read_model(model_dir)
    root = images_dir or _image_root(path, model_dir, min((v[3] for v in imgs.values()), default=None))
    mask_root = os.path.join(os.path.dirname(root), "masks")
    listing, cameras_file = _model_file(model_dir, "images")[0], _model_file(model_dir, "cameras")[0]
    stack = ImageStack(downscale, parse_background(background), source=listing)
    for iid, (q, t, cid, name) in sorted(imgs.items(), key=lambda kv: kv[1][3]):
        image_file = os.path.join(root, name)
        if not os.path.isfile(image_file):
            stack.skip(name)
            continue
        i = len(stack.cameras)  # the camera's index in the scene
        if cid not in cams:
            raise ValueError(f"COLMAP image {iid} ({name!r}) in {listing} refers to camera {cid}, which "
                             f"{cameras_file} lacks")
        model, w, h, params = cams[cid]
        K, d = _intrinsics(cid, model, params)
        w2c = np.eye(4)
        if not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0:
            raise ValueError(f"camera {i} ({name!r}) in {listing}: COLMAP quaternion must be finite and non-zero, "
                             f"got {list(q)}")
        w2c[:3, :3] = qvec_to_rotmat(q)
        w2c[:3, 3] = t
        cam = make_camera(i, name, K, w2c, w, h, d, source=cameras_file)
        mask = None
        for mp in (os.path.join(mask_root, name), os.path.join(mask_root, name + ".png")):
            if os.path.isfile(mp):
                mask = read_mask(mp)
                break
        stack.add(cam, read_image(image_file), mask)  # RGBA: composited onto the background, alpha is the mask
    cameras, images, masks = stack.arrays()
    points, colors = (None, None) if pts is None or len(pts[0]) == 0 else pts
    return Scene(cameras, images, masks=masks, points=points, point_colors=colors,
                 background=stack.background, name=os.path.basename(os.path.normpath(path)))
