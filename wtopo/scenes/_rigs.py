# SPDX-License-Identifier: Apache-2.0
"""Camera rigs around an object for synthetic scenes: full sphere, upper hemisphere, a 360 orbit and a
forward-facing grid (:func:`rig_cameras`)."""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera

RIGS = ("sphere", "hemisphere", "orbit", "forward")


_FIT_MARGIN = 1.15  # camera distance keeps the bounding sphere this much inside the narrower field of view


_ORBIT_ELEVATION = 25.0  # degrees: the orbit rig's default ring sees the top and the sides of an object


def _frame_from_up(up) -> np.ndarray:
    """Rows (right, up, front): an orthonormal frame whose second axis is ``up``."""
    u = np.asarray(up, dtype=np.float64)
    nu = np.linalg.norm(u)
    if u.shape != (3,) or not np.isfinite(nu) or nu == 0:
        raise ValueError(f"up must be a non-zero 3-vector, got {up!r}")
    u = u / nu
    a = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(u, a)
    right /= np.linalg.norm(right)
    front = np.cross(right, u)
    return np.stack([right, u, front])


def _fibonacci(n: int, z_lo: float, z_hi: float, phase: float) -> np.ndarray:
    """N directions (right, up, front coords) evenly spread over the band up-component in [z_lo, z_hi]."""
    k = np.arange(n) + 0.5
    z = z_hi - (z_hi - z_lo) * k / n
    r = np.sqrt(np.clip(1 - z * z, 0, None))
    phi = k * math.pi * (3 - math.sqrt(5)) + phase  # golden angle
    return np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)


def rig_cameras(rig: str, n_views: int, center, radius: float, *, resolution, up=(0, 0, 1), fov: float = 0.7,
                seed: int = 0, elevation: float = _ORBIT_ELEVATION) -> list[Camera]:
    """Cameras looking at a bounding sphere (``center``, ``radius``) from a rig.

    Args:
        rig: ``"sphere"`` (Fibonacci over the full sphere), ``"hemisphere"`` (upper half, 5 to 80
            degrees elevation), ``"orbit"`` (one ring at ``elevation``) or ``"forward"``
            (parallel cameras on a grid in front of the object, LLFF-like).
        n_views: number of cameras (>= 1).
        center: sphere centre [3], world units.
        radius: sphere radius, world units.
        resolution: image size as ``int`` (square) or ``(width, height)``.
        up: world up direction.
        fov: field of view of the narrower image side, radians.
        seed: rotates the rig about ``up`` (deterministic).
        elevation: the orbit ring's elevation above the horizontal plane through ``center``, degrees
            in (-90, 90).
    """
    if rig not in RIGS:
        raise ValueError(f"rig must be one of {RIGS}, got {rig!r}")
    if isinstance(n_views, bool) or int(n_views) != n_views or n_views < 1:
        raise ValueError(f"n_views must be a positive integer, got {n_views!r}")
    w, h = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
    if int(w) != w or int(h) != h or w < 1 or h < 1:
        raise ValueError(f"resolution must be a positive int or (width, height), got {resolution!r}")
    w, h = int(w), int(h)
    if not (0 < fov < math.pi):
        raise ValueError(f"fov must be in (0, pi) radians, got {fov!r}")
    if not (-90 < elevation < 90):
        raise ValueError(f"elevation must be in (-90, 90) degrees, got {elevation!r}")
    frame = _frame_from_up(up)
    c = np.asarray(center, dtype=np.float64)
    phase = np.random.default_rng(seed).uniform(0, 2 * math.pi)
    dist = _FIT_MARGIN * radius / math.sin(0.5 * fov)
    fov_x = 2 * math.atan(math.tan(0.5 * fov) * w / min(w, h))
    n = int(n_views)
    if rig == "forward":
        cols = math.ceil(math.sqrt(n))
        rows = math.ceil(n / cols)
        k = np.arange(n)
        gx = (k % cols - 0.5 * (cols - 1)) / max(cols - 1, 1)
        gy = (k // cols - 0.5 * (rows - 1)) / max(rows - 1, 1)
        eyes = c - dist * frame[2] + radius * (gx[:, None] * frame[0] + gy[:, None] * frame[1])
        targets = eyes + frame[2]
    else:
        if rig == "sphere":
            d = _fibonacci(n, -1.0, 1.0, phase)
        elif rig == "hemisphere":
            d = _fibonacci(n, math.sin(math.radians(5)), math.sin(math.radians(80)), phase)
        else:
            a = phase + 2 * math.pi * np.arange(n) / n
            e = math.radians(elevation)
            d = np.stack([math.cos(e) * np.cos(a), np.full(n, math.sin(e)), math.cos(e) * np.sin(a)], axis=1)
        eyes = c + dist * (d @ frame)
        targets = np.broadcast_to(c, eyes.shape)
    return [Camera.look_at(eyes[i], targets[i], frame[1], fov_x=fov_x, width=w, height=h, name=f"{rig}_{i:03d}")
            for i in range(n)]
