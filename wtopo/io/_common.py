# SPDX-License-Identifier: Apache-2.0
"""Helpers written once for the whole package: array coercion, quaternion maths, the degree-0
SH colour convention and atomic files (used by the PLY / USD writers, the fit's checkpoints and
its JSON outputs)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable

import numpy as np

__all__ = ["as_array", "quat_normal", "sh_dc_to_rgb", "rgb_to_sh_dc", "atomic_write", "SH_C0"]

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonic constant ``1 / (2 sqrt(pi))``: ``rgb = 0.5 + SH_C0 * f_dc``."""


def as_array(name: str, value, *, shape, dtype=np.float32, finite: bool = True) -> np.ndarray:
    """Coerce a torch tensor / array-like to a contiguous NumPy array and check its shape.

    Args:
        name: argument name used in error messages.
        value: torch tensor (any device; detached and copied to host) or array-like.
        shape: expected shape; ``None`` entries match any size.
        dtype: NumPy dtype of the result.
        finite: when True, raise on NaN/inf.

    Raises:
        TypeError: ``value`` is not numeric.
        ValueError: wrong shape or non-finite values.
    """
    if hasattr(value, "detach") and hasattr(value, "cpu"):
        value = value.detach().cpu().numpy()
    try:
        a = np.ascontiguousarray(np.asarray(value), dtype=dtype)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(a.shape)}")
    if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        idx = [int(i) for i in np.argwhere(~np.isfinite(a))[0]]
        raise ValueError(f"{name} must be finite, got {a[tuple(idx)]} at index {idx}")
    return a


def normalize_quats(quats: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] (w, x, y, z); a zero quaternion becomes the identity."""
    n = np.linalg.norm(quats, axis=1, keepdims=True)
    out = np.where(n > 0, quats / np.where(n > 0, n, 1), np.array([1, 0, 0, 0], dtype=quats.dtype))
    return out.astype(quats.dtype, copy=False)


def quat_normal(quats: np.ndarray) -> np.ndarray:
    """Local +z axis of each rotation (the surfel normal) [N, 3] from quaternions [N, 4] (w, x, y, z)."""
    w, x, y, z = normalize_quats(np.asarray(quats, dtype=np.float64)).T
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)


def sh_dc_to_rgb(dc):
    """Base colour in [0, 1] of degree-0 SH coefficients (3DGS convention, clipped).

    Args:
        dc: degree-0 coefficients [..., 3], a NumPy array or a torch tensor (any device).

    Returns:
        The colours, same shape and type as ``dc``.
    """
    return (0.5 + SH_C0 * dc).clip(0.0, 1.0)


def rgb_to_sh_dc(rgb):
    """Degree-0 SH coefficients whose base colour is ``rgb`` (inverse of :func:`sh_dc_to_rgb` on [0, 1]).

    Args:
        rgb: colours [..., 3] in [0, 1], a NumPy array or a torch tensor (any device).

    Returns:
        The coefficients, same shape and type as ``rgb``.
    """
    return (rgb - 0.5) / SH_C0


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], *,
                 verify: Callable[[str], None] | None = None, suffix: str = "") -> str:
    """Write a file through a temporary sibling, verify it, then rename it over ``path``.

    ``write(tmp_path)`` produces the file; ``verify(tmp_path)`` raises if it is wrong.  The
    temporary file is fsynced before the rename and the directory after it (design/stability.md,
    "Not losing work"); on any exception the temporary file is removed and ``path`` is left
    untouched.  The one atomic write of the package: PLY, USD, exports, reports, the fit's JSON
    files and its checkpoints all go through it.

    Args:
        path: the final file.
        write: writes the whole file at the temporary path it is given.
        verify: optional check of the temporary file; raises when it is wrong.
        suffix: suffix of the temporary file (writers that pick the format from it need it).

    Returns:
        ``path`` as a string.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=suffix or ".tmp", dir=directory)
    os.close(fd)
    try:
        write(tmp)
        if verify is not None:
            verify(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:  # directories cannot be opened on some platforms (Windows)
        return path
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
    return path
