# SPDX-License-Identifier: Apache-2.0
"""Camera model: OpenCV axes, pinhole intrinsics with any principal point, optional OpenCV
radial-tangential distortion, and per-pixel world rays (so every renderer takes any camera).

Conventions:
    * camera axes are OpenCV's: +x right, +y down, +z forward;
    * ``world_to_camera`` maps homogeneous world points to camera coordinates;
    * continuous pixel coordinates put the centre of pixel ``(row i, column j)`` at
      ``(u, v) = (j + 0.5, i + 0.5)`` (COLMAP's convention; Blender's ``cx = W / 2`` is the image
      centre under it);
    * distortion follows OpenCV: ``(k1, k2, p1, p2[, k3])`` applied to normalised coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is imported where rays are made: the USD writer's process reads cameras without it
    import torch

__all__ = ["Camera"]

_ORTHO_TOL = 1e-4  # |R R^T - I| tolerated from float32 round trips of exported poses


def _as_matrix(name: str, value, shape) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a numeric array of shape {list(shape)}, got {type(value).__name__}") from None
    if a.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {list(shape)}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name} must be finite, got {a[idx]} at index {list(idx)}")
    return a


@dataclass
class Camera:
    """A posed camera.

    Args:
        K: intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels, shape [3, 3], float64.
        world_to_camera: rigid transform, shape [4, 4], float64, world units.
        width: image width in pixels.
        height: image height in pixels.
        distortion: OpenCV ``(k1, k2, p1, p2[, k3])`` or ``None`` for a pinhole camera.
        name: optional label (image file name).

    Raises:
        ValueError: NaN/inf entries, a rotation that is not orthonormal or has det -1,
            focal lengths <= 0, a non-positive size.

    Limitations:
        Fisheye and other non-OpenCV models must be converted to per-pixel rays by the caller
        (:meth:`pixel_rays` is the only place the lens model enters the renderers).
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    distortion: np.ndarray | None = None
    name: str = ""
    _rays_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.K = _as_matrix("K", self.K, (3, 3))
        self.world_to_camera = _as_matrix("world_to_camera", self.world_to_camera, (4, 4))
        for nm in ("width", "height"):
            v = getattr(self, nm)
            if isinstance(v, bool) or int(v) != v or int(v) <= 0:
                raise ValueError(f"{nm} must be a positive integer, got {v!r}")
            setattr(self, nm, int(v))
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"K focal lengths must be > 0, got fx={self.K[0, 0]}, fy={self.K[1, 1]}")
        K = self.K
        if abs(K[2, 2] - 1.0) > 1e-9 or abs(K[2, 0]) > 1e-12 or abs(K[2, 1]) > 1e-12 or abs(K[1, 0]) > 1e-12:
            raise ValueError(f"K must have last row [0, 0, 1] and K[1,0] = 0, got {self.K.tolist()}")
        R = self.world_to_camera[:3, :3]
        err = np.abs(R @ R.T - np.eye(3)).max()
        if err > _ORTHO_TOL:
            raise ValueError(f"world_to_camera rotation must be orthonormal, got |R R^T - I| = {err:.3g}")
        det = np.linalg.det(R)
        if det < 0:
            raise ValueError(f"world_to_camera rotation must have det +1 (a reflection was given), got det = {det:.6f}")
        if np.abs(self.world_to_camera[3] - np.array([0, 0, 0, 1.0])).max() > 1e-9:
            raise ValueError(f"world_to_camera last row must be [0, 0, 0, 1], got {self.world_to_camera[3].tolist()}")
        if self.distortion is not None:
            d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
            if d.size not in (4, 5):
                raise ValueError(f"distortion must hold (k1, k2, p1, p2[, k3]), got {d.size} values")
            if not np.all(np.isfinite(d)):
                raise ValueError(f"distortion must be finite, got {d.tolist()}")
            d = np.concatenate([d, np.zeros(5 - d.size)])
            self.distortion = None if not np.any(d) else d

    # -- pose ------------------------------------------------------------------------------
    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotation [3, 3]."""
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> np.ndarray:
        """World-to-camera translation [3]."""
        return self.world_to_camera[:3, 3]

    @property
    def camera_to_world(self) -> np.ndarray:
        """Inverse pose [4, 4] (columns: camera +x, +y, +z axes and centre in world)."""
        m = np.eye(4)
        m[:3, :3] = self.R.T
        m[:3, 3] = -self.R.T @ self.t
        return m

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [3]."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (+z axis of the camera) in world coordinates [3]."""
        return self.R[2].copy()

    # -- lens ------------------------------------------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply the lens distortion to normalised coordinates ``xy`` [..., 2] (float64)."""
        if self.distortion is None:
            return xy
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xyd: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Invert :meth:`distort` by Newton's method on normalised coordinates [..., 2] (float64)."""
        if self.distortion is None or xyd.size == 0:
            return xyd
        k1, k2, p1, p2, k3 = self.distortion
        xy = xyd.copy()
        for _ in range(iterations):
            x, y = xy[..., 0], xy[..., 1]
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
            f = self.distort(xy) - xyd
            # Jacobian of distort
            j00 = radial + x * dradial * 2 * x + 2 * p1 * y + p2 * 6 * x
            j01 = x * dradial * 2 * y + 2 * p1 * x + p2 * 2 * y
            j10 = y * dradial * 2 * x + p1 * 2 * x + 2 * p2 * y
            j11 = radial + y * dradial * 2 * y + p1 * 6 * y + 2 * p2 * x
            det = j00 * j11 - j01 * j10
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx = (j11 * f[..., 0] - j01 * f[..., 1]) / det
            dy = (-j10 * f[..., 0] + j00 * f[..., 1]) / det
            xy = xy - np.stack([dx, dy], axis=-1)
            if np.max(np.abs(f)) < 1e-14:
                break
        return xy

    # -- rays and projection ---------------------------------------------------------------
    def pixel_directions_camera(self, rows: np.ndarray | None = None, cols: np.ndarray | None = None) -> np.ndarray:
        """Ray directions in camera axes, float64, scaled so that z = 1: through every pixel centre [H, W, 3], or
        through the centres of the pixels at integer ``rows`` and ``cols`` (two arrays of one shape S) [*S, 3]. With
        a lens distortion the two agree to float64 rounding (the Newton inversion stops when all its pixels have
        converged), without one bit for bit."""
        if (rows is None) != (cols is None):
            raise ValueError("pixel_directions_camera needs both rows and cols, or neither")
        if rows is None:
            j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        else:
            i, j = np.asarray(rows, np.float64) + 0.5, np.asarray(cols, np.float64) + 0.5
        fx, s, cx = self.K[0]
        fy, cy = self.K[1, 1], self.K[1, 2]
        y = (i - cy) / fy
        x = (j - cx - s * y) / fx
        xy = self.undistort(np.stack([x, y], axis=-1))
        return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)

    def cached(self, key, build):
        """``build()`` computed once per ``key`` and kept on this camera (derived per-device tensors
        that ops would otherwise copy to the device on every call); ``key`` must name the device."""
        if key not in self._rays_cache:
            self._rays_cache[key] = build()
        return self._rays_cache[key]

    def pixel_rays(self, device: torch.device | str = "cpu", dtype: torch.dtype | None = None):
        """World-frame rays through every pixel centre.

        Returns:
            ``(origins, directions)``, each [H, W, 3] of ``dtype`` (default ``torch.float32``) on
            ``device``. Directions are *not* unit length: their camera-z component is 1, so the ray
            parameter of a hit is its z-depth in this camera. Cached per (device, dtype).
        """
        import torch

        dtype = torch.float32 if dtype is None else dtype

        def build():
            d_world = self.pixel_directions_camera() @ self.R  # == (R^T d)^T
            o = np.broadcast_to(self.center, d_world.shape)
            return (torch.as_tensor(np.ascontiguousarray(o), dtype=dtype, device=device),
                    torch.as_tensor(np.ascontiguousarray(d_world), dtype=dtype, device=device))

        return self.cached((str(device), dtype), build)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [N, 3] to continuous pixel coordinates [N, 2] and z-depth [N] (float64)."""
        p = np.asarray(points, dtype=np.float64) @ self.R.T + self.t
        z = p[:, 2]
        zs = np.where(np.abs(z) < 1e-300, 1e-300, z)
        xy = self.distort(p[:, :2] / zs[:, None])
        u = self.K[0, 0] * xy[:, 0] + self.K[0, 1] * xy[:, 1] + self.K[0, 2]
        v = self.K[1, 1] * xy[:, 1] + self.K[1, 2]
        return np.stack([u, v], axis=1), z

    def transformed(self, scale: float, translation: np.ndarray) -> Camera:
        """This camera seen in coordinates ``x' = scale * (x + translation)`` (a similarity)."""
        c2w = self.camera_to_world
        c2w[:3, 3] = scale * (c2w[:3, 3] + np.asarray(translation, dtype=np.float64))
        w2c = np.linalg.inv(c2w)
        w2c[3] = [0, 0, 0, 1]
        return Camera(self.K.copy(), w2c, self.width, self.height,
                      None if self.distortion is None else self.distortion.copy(), self.name)

    def scaled(self, factor: float) -> Camera:
        """The same camera with the image resized by ``factor`` (intrinsics scaled)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        K = self.K.copy()
        K[0] *= w / self.width
        K[1] *= h / self.height
        K[2] = [0, 0, 1]
        return Camera(K, self.world_to_camera.copy(), w, h,
                      None if self.distortion is None else self.distortion.copy(), self.name)

    @staticmethod
    def look_at(eye, target, up, *, fov_x: float, width: int, height: int, name: str = "") -> Camera:
        """A pinhole camera at ``eye`` looking at ``target`` (OpenCV axes; ``up`` is world up, fov in radians)."""
        eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
        z = target - eye
        nz = np.linalg.norm(z)
        if nz == 0:
            raise ValueError("look_at: eye and target must differ")
        z /= nz
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
            x = np.cross(z, np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0]))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        w2c = np.eye(4)
        w2c[:3, :3] = np.stack([x, y, z])
        w2c[:3, 3] = -w2c[:3, :3] @ eye
        f = 0.5 * width / np.tan(0.5 * fov_x)
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        return Camera(K, w2c, width, height, None, name)
