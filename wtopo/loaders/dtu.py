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


def _frame_numbers(files: list[str]) -> list[int] | None:
    """The frame number of each file (``000012.png`` -> 12) when every stem is a distinct integer, else ``None``."""
    stems = [os.path.splitext(os.path.basename(f))[0] for f in files]
    if not all(st.isdigit() for st in stems):
        return None
    nums = [int(st) for st in stems]
    return nums if len(set(nums)) == len(nums) else None


def load_dtu(path: str, *, background=None, downscale: float = 1, cameras_file: str | None = None):
    """Read one DTU scan folder (IDR / NeuS layout).

    Image ``i`` takes ``world_mat_i``, where ``i`` is the number its file is named by (``000012.png``)
    when every image is named by the number of a camera in the file, else its position in name
    order (IDR). Masks pair with images by the same number (NeuS names images ``000012.png`` and
    masks ``012.png``). With numbered files, cameras whose image is missing are skipped with one
    warning naming them.

    Args:
        path: scan folder with ``image/`` or ``images/``, optional ``mask/``, and the cameras file.
        background: constant background colour, or ``None`` (DTU images show a real background).
        downscale: image size divisor (>= 1).
        cameras_file: ``cameras_sphere.npz`` (default when present) or ``cameras.npz``.

    Returns:
        :class:`wtopo.Scene` in DTU world millimetres, ``bounds`` = box of the ``scale_mat`` unit sphere.

    Raises:
        ValueError: an image without its ``world_mat`` or mask, a non-finite projection, a
            principal point far outside the image (e.g. 1600x1200 intrinsics with downscaled
            images), an unreadable image, fewer than
            :data:`~wtopo.loaders._common.MIN_IMAGES_AFTER_SKIPPING` images left after skipping.
    """
    from ..scene import Scene
    from ._common import parse_background

    cf = cameras_file or next((f for f in ("cameras_sphere.npz", "cameras.npz")
                               if os.path.isfile(os.path.join(path, f))), None)
    if cf is None:
        raise FileNotFoundError(f"no cameras_sphere.npz or cameras.npz in {path}")
    source = os.path.join(path, cf)
    try:
        data = np.load(source)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read {source}: {e}") from e
    images = _listing(path, ("image", "images"))
    if not images:
        raise FileNotFoundError(f"no images in {path}/image or {path}/images")
    masks = _listing(path, ("mask", "masks"))
    prefix = "world_mat_"
    listed = {int(k[len(prefix):]) for k in data.files if k.startswith(prefix) and k[len(prefix):].isdigit()}
    numbers = _frame_numbers(images)
    mask_numbers = _frame_numbers(masks) if masks else None
    if numbers is not None and set(numbers) <= listed and (not masks or mask_numbers is not None):
        mask_of = dict(zip(mask_numbers, masks)) if masks else {}
        missing = sorted(listed - set(numbers))
    else:  # pair by position, as IDR does; which camera lacks its image cannot be told
        if masks and len(masks) != len(images):
            raise ValueError(f"{path} has {len(images)} images but {len(masks)} masks")
        numbers = list(range(len(images)))
        mask_of = dict(zip(numbers, masks))
        missing = []
    stack = ImageStack(downscale, parse_background(background), source=source)
    for n in missing:
        stack.skip(f"world_mat_{n}")
    scale0 = None
    for n, ip in zip(numbers, images):
        key = f"world_mat_{n}"
        i = len(stack.cameras)  # the camera's index in the scene
        name = os.path.basename(ip)
        if key not in data:
            raise ValueError(f"{source} lacks {key} for image {name}")
        P = data[key]
        if not np.all(np.isfinite(P)):
            raise ValueError(f"camera {i} ({name}) in {source}: {key} must be finite, got {P.tolist()}")
        if masks and n not in mask_of:
            raise ValueError(f"image {name} has no mask in {os.path.dirname(masks[0])}")
        K, w2c = decompose_projection(P)
        img = read_image(ip)
        h, w = img.shape[:2]
        cam = make_camera(i, name, K, w2c, w, h, source=source)
        if scale0 is None:
            scale0 = np.asarray(data.get(f"scale_mat_{n}", np.eye(4)), dtype=np.float64)
        stack.add(cam, img[..., :3], read_mask(mask_of[n]) if masks else None)
    cameras, imgs, msk = stack.arrays()
    c, r = scale0[:3, 3], scale0[0, 0]
    return Scene(cameras, imgs, masks=msk, bounds=(c - r, c + r), background=stack.background,
                 name=os.path.basename(os.path.normpath(path)), info={"scale_mat": scale0})
