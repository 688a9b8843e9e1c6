# SPDX-License-Identifier: Apache-2.0
"""DTU in the IDR / NeuS layout: ``image/`` (or ``images/``), ``mask/`` and ``cameras_sphere.npz``
(or ``cameras.npz``) holding ``world_mat_i`` (the 4x4 projection ``K [R | t]`` from DTU world
millimetres to pixels) and ``scale_mat_i`` (maps the unit sphere around the object into that
world).

The projection is decomposed with an RQ decomposition written in NumPy (no OpenCV). The scene's
world frame is the DTU millimetre frame itself, so meshes fitted on it are directly comparable with
the DTU point clouds; ``scale_mat`` gives the region of interest (the unit sphere's box) and is kept
in ``scene.info["scale_mat"]``.
"""

from __future__ import annotations

import glob
import os

import numpy as np

from ._common import ImageStack, make_camera, read_image, read_mask

__all__ = ["load_dtu", "rq", "decompose_projection"]


def rq(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition ``M = U Q`` of a 3x3 matrix: ``U`` upper triangular with a non-negative
    diagonal, ``Q`` orthogonal (float64)."""
    M = np.asarray(M, dtype=np.float64)
    P = np.eye(3)[::-1]  # reversal permutation: turns QR of (P M)^T into RQ of M
    q, r = np.linalg.qr((P @ M).T)
    U = P @ r.T @ P
    Q = P @ q.T
    S = np.diag(np.where(np.diag(U) < 0, -1.0, 1.0))
    return U @ S, S @ Q


def decompose_projection(P) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 (or 4x4) projection ``P ~ K [R | t]`` into ``K`` [3, 3] (``K[2, 2] = 1``) and a
    world-to-camera [4, 4] with ``det R = +1`` (float64)."""
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    if np.linalg.det(P[:, :3]) < 0:  # projective scale -1: same camera, makes det R = +1
        P = -P
    K, R = rq(P[:, :3])
    t = np.linalg.solve(K, P[:, 3])
    K = K / K[2, 2]
    K[1, 0] = K[2, 0] = K[2, 1] = 0.0
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, t
    return K, w2c


def _listing(path: str, names) -> list[str]:
    for n in names:
        d = os.path.join(path, n)
        if os.path.isdir(d):
            files = sorted(f for e in ("png", "jpg", "PNG", "JPG") for f in glob.glob(os.path.join(d, f"*.{e}")))
            if files:
                return files
    return []


def load_dtu(path: str, *, background=None, downscale: float = 1, cameras_file: str | None = None):
    """Read one DTU scan folder (IDR / NeuS layout).

    Args:
        path: scan folder with ``image/`` or ``images/``, optional ``mask/``, and the cameras file.
        background: constant background colour, or ``None`` (DTU images show a real background).
        downscale: image size divisor (>= 1).
        cameras_file: ``cameras_sphere.npz`` (default when present) or ``cameras.npz``.

    Returns:
        :class:`wtopo.Scene` in DTU world millimetres, ``bounds`` = box of the ``scale_mat`` unit sphere.
    """
    from ..scene import Scene
    from ._common import parse_background

    cf = cameras_file or next((f for f in ("cameras_sphere.npz", "cameras.npz")
                               if os.path.isfile(os.path.join(path, f))), None)
    if cf is None:
        raise FileNotFoundError(f"no cameras_sphere.npz or cameras.npz in {path}")
    data = np.load(os.path.join(path, cf))
    images = _listing(path, ("image", "images"))
    if not images:
        raise FileNotFoundError(f"no images in {path}/image or {path}/images")
    masks = _listing(path, ("mask", "masks"))
    if masks and len(masks) != len(images):
        raise ValueError(f"{path} has {len(images)} images but {len(masks)} masks")
    stack = ImageStack(downscale, parse_background(background))
    scale0 = None
    for i, ip in enumerate(images):
        key = f"world_mat_{i}"
        if key not in data:
            raise ValueError(f"{cf} lacks {key} for image {i} ({os.path.basename(ip)})")
        P = data[key]
        if not np.all(np.isfinite(P)):
            raise ValueError(f"camera {i} ({os.path.basename(ip)}): {key} must be finite, got {P.tolist()}")
        K, w2c = decompose_projection(P)
        img = read_image(ip)
        h, w = img.shape[:2]
        cam = make_camera(i, os.path.basename(ip), K, w2c, w, h)
        if scale0 is None:
            scale0 = np.asarray(data.get(f"scale_mat_{i}", np.eye(4)), dtype=np.float64)
        stack.add(cam, img[..., :3], read_mask(masks[i]) if masks else None)
    cameras, imgs, msk = stack.arrays()
    c, r = scale0[:3, 3], scale0[0, 0]
    return Scene(cameras, imgs, masks=msk, bounds=(c - r, c + r), background=stack.background,
                 name=os.path.basename(os.path.normpath(path)), info={"scale_mat": scale0})
