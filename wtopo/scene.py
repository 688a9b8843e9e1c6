# SPDX-License-Identifier: Apache-2.0
"""Posed image sets (:class:`Scene`) and the similarity (:class:`Similarity`) that maps a scene
into wtopo's internal frame, where the region of interest fits the unit cube ``[0, 1]^3`` with a
margin so that Poisson reconstruction and marching cubes run on it directly.

All world maths runs in float64 on the host; results go back to the caller's frame and units
through :meth:`Similarity.to_world`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ._validate import all_finite
from .camera import Camera
from .geometry.region import points_box, visual_hull_box

__all__ = ["Scene", "Similarity", "NORMALIZATION_MARGIN"]

NORMALIZATION_MARGIN = 0.1
"""Empty border, on every side of the unit cube, that :meth:`Scene.normalization` leaves around the
region of interest (which then fills ``[0.1, 0.9]^3``): room for surfels at the region's boundary and
for the Poisson padding, so the indicator field does not wrap onto the opposite face."""

_IMAGE_RANGE_TOL = 1e-4  # images outside [0, 1] by less than this (float rounding of composites) are clipped
_UNIT_NORMAL_TOL = 1e-2  # normals must be unit (or 0 = invalid) within this (float32 exports)


def _to_numpy64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy().astype(np.float64)
    return np.asarray(x, dtype=np.float64)


@dataclass(frozen=True)
class Similarity:
    """A uniform scale plus translation between the user's (world) frame and wtopo's internal frame.

    ``internal = scale * (world + translation)`` and ``world = internal / scale - translation``
    (the convention of :meth:`wtopo.Camera.transformed`). Held in float64.

    Args:
        scale: positive uniform scale (internal units per world unit).
        translation: world-frame offset, shape [3], world units.
    """

    scale: float
    translation: tuple

    def __post_init__(self):
        s = float(self.scale)
        if not math.isfinite(s) or s <= 0:
            raise ValueError(f"Similarity.scale must be finite and > 0, got {self.scale!r}")
        t = np.asarray(self.translation, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"Similarity.translation must be 3 finite numbers, got {self.translation!r}")
        object.__setattr__(self, "scale", s)
        object.__setattr__(self, "translation", tuple(float(v) for v in t))

    @staticmethod
    def identity() -> Similarity:
        """The identity map."""
        return Similarity(1.0, (0.0, 0.0, 0.0))

    @property
    def t(self) -> np.ndarray:
        """Translation as a float64 array [3]."""
        return np.asarray(self.translation, dtype=np.float64)

    def matrix(self) -> np.ndarray:
        """The world-to-internal map as a homogeneous float64 matrix [4, 4]."""
        m = np.eye(4)
        m[:3, :3] *= self.scale
        m[:3, 3] = self.scale * self.t
        return m

    def inverse(self) -> Similarity:
        """The internal-to-world map as a :class:`Similarity`."""
        return Similarity(1.0 / self.scale, tuple(-self.scale * self.t))

    def compose(self, inner: Similarity) -> Similarity:
        """``self`` applied after ``inner`` (x -> self(inner(x)))."""
        # self(inner(x)) = s2 * (s1 * (x + t1) + t2) = s2 s1 (x + t1 + t2 / s1)
        return Similarity(self.scale * inner.scale, tuple(inner.t + self.t / inner.scale))

    def _map(self, x, forward: bool):
        import trimesh

        if isinstance(x, Camera):
            if forward:
                return x.transformed(self.scale, self.t)
            inv = self.inverse()
            return x.transformed(inv.scale, inv.t)
        if isinstance(x, trimesh.Trimesh):
            out = x.copy()
            out.vertices = self._map(np.asarray(x.vertices, dtype=np.float64), forward)
            return out
        if isinstance(x, torch.Tensor):
            y = self._map(x.detach().cpu().numpy().astype(np.float64), forward)
            return torch.as_tensor(y, dtype=x.dtype, device=x.device)
        a = np.asarray(x, dtype=np.float64)
        if a.ndim == 0 or a.shape[-1] != 3:
            raise ValueError(f"points must have shape [..., 3], got {list(a.shape)}")
        if forward:
            return self.scale * (a + self.t)
        return a / self.scale - self.t

    def to_internal(self, x):
        """Map world points ([..., 3] numpy / torch, computed in float64 and returned in the input's
        dtype), a :class:`~wtopo.Camera` or a ``trimesh.Trimesh`` into the internal frame."""
        return self._map(x, True)

    def to_world(self, x):
        """Inverse of :meth:`to_internal` (same accepted types)."""
        return self._map(x, False)

    def length_to_world(self, d):
        """Scale a length from internal to world units."""
        return d / self.scale


def _as_float_tensor(name: str, x, shape_tail: tuple, n: int | None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x.detach()
        if not t.is_floating_point():
            t = t.float()
        t = t.to(torch.float32)
    else:
        try:
            t = torch.from_numpy(np.ascontiguousarray(np.asarray(x, dtype=np.float32)))
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be a numeric array, got {type(x).__name__}") from None
    want = len(shape_tail) + 1
    if t.ndim != want or (n is not None and t.shape[0] != n) or any(
            s is not None and s != a for s, a in zip(shape_tail, t.shape[1:])):
        dims = ["N" if n is None else str(n)] + ["*" if s is None else str(s) for s in shape_tail]
        desc = "[" + ", ".join(dims) + "]"
        raise ValueError(f"{name} must have shape {desc}, got {list(t.shape)}")
    return t


def _first_bad(name: str, t: torch.Tensor, bad: torch.Tensor, what: str):
    idx = [int(i) for i in torch.nonzero(bad)[0].tolist()]
    raise ValueError(f"{name} must be {what}, got {t[tuple(idx)].item()} at index {idx} (image {idx[0]})")


def _camera_error(i: int, cam: Camera, msg: str) -> ValueError:
    label = f" ({cam.name!r})" if getattr(cam, "name", "") else ""
    return ValueError(f"cameras[{i}]{label}: {msg}")


@dataclass(eq=False)
class Scene:
    """Posed images of one scene, validated on construction.

    Args:
        cameras: one :class:`~wtopo.Camera` per image, all of the images' size.
        images: colours in [0, 1], shape [N, H, W, 3], float32 (numpy or torch; stored as a torch
            tensor on the given device).
        masks: foreground masks, shape [N, H, W], bool, or ``None``.
        depths: z-depth in world units, shape [N, H, W], float32; 0 = invalid (NaN/inf entries are
            stored as 0).
        normals: world-frame unit normals, shape [N, H, W, 3], float32; 0 = invalid.
        gt_mesh: ground-truth surface (``trimesh.Trimesh``) in the world frame, for metrics only.
        bounds: region of interest ``(lower [3], upper [3])`` in world units, or ``None``.
        points: initial points, shape [P, 3], world units (e.g. COLMAP ``points3D``).
        point_colors: their colours in [0, 1], shape [P, 3].
        background: constant background colour (3 floats in [0, 1]) the images were composited
            on, or ``None`` (a real background is visible).
        name: label.
        train_indices: image indices used for fitting, or ``None`` (all).
        test_indices: held-out image indices, or ``None``.
        info: free-form metadata from the loader (e.g. DTU's ``scale_mat``).

    Raises:
        ValueError: a camera with NaN/inf entries, a non-orthonormal or reflecting rotation,
            focal length <= 0 or a size other than the images' (the message names the camera index
            and the value); arrays of the wrong shape or out of range.

    Limitations:
        All images share one size; rescale them first (or load with ``downscale``).
    """

    cameras: list
    images: object
    masks: object = None
    depths: object = None
    normals: object = None
    gt_mesh: object = None
    bounds: object = None
    points: object = None
    point_colors: object = None
    background: object = None
    name: str = ""
    train_indices: object = None
    test_indices: object = None
    info: dict = field(default_factory=dict)
    _norm_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _roi_cache: list = field(default_factory=list, init=False, repr=False, compare=False)

    def __post_init__(self):
        cams = list(self.cameras) if not isinstance(self.cameras, Camera) else [self.cameras]
        if len(cams) == 0:
            raise ValueError("cameras must hold at least one Camera, got an empty list")
        checked = []
        for i, cam in enumerate(cams):
            if not isinstance(cam, Camera):
                raise TypeError(f"cameras[{i}] must be a wtopo.Camera, got {type(cam).__name__}")
            try:  # re-validate: the fields may have been edited after construction
                checked.append(Camera(cam.K, cam.world_to_camera, cam.width, cam.height, cam.distortion, cam.name))
            except ValueError as e:
                raise _camera_error(i, cam, str(e)) from None
        self.cameras = checked
        n = len(checked)

        img = _as_float_tensor("images", self.images, (None, None, 3), n)
        H, W = int(img.shape[1]), int(img.shape[2])
        for i, cam in enumerate(checked):
            if cam.width != W or cam.height != H:
                raise _camera_error(i, cam, f"size {cam.width}x{cam.height} (WxH) does not match the images' {W}x{H}")
        if not all_finite(img):  # one reduction; the indexed search only on failure
            _first_bad("images", img, ~torch.isfinite(img), "finite")
        bad = (img < -_IMAGE_RANGE_TOL) | (img > 1 + _IMAGE_RANGE_TOL)
        if bool(bad.any()):
            _first_bad("images", img, bad, "in [0, 1]")
        self.images = img.clamp(0.0, 1.0).contiguous()
        dev = self.images.device

        if self.masks is not None:
            m = self.masks
            m = m.detach() if isinstance(m, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(np.asarray(m)))
            if m.dtype != torch.bool:
                if bool(((m != 0) & (m != 1)).any()):
                    other = m[(m != 0) & (m != 1)][0].item()
                    raise ValueError(f"masks must be bool or 0/1, got values such as {other}")
                m = m != 0
            if tuple(m.shape) != (n, H, W):
                raise ValueError(f"masks must have shape [{n}, {H}, {W}], got {list(m.shape)}")
            self.masks = m.to(dev).contiguous()
        if self.depths is not None:
            d = _as_float_tensor("depths", self.depths, (H, W), n)
            d = torch.where(torch.isfinite(d), d, torch.zeros_like(d))
            if bool((d < 0).any()):
                _first_bad("depths", d, d < 0, ">= 0 (0 = invalid)")
            self.depths = d.to(dev).contiguous()
        if self.normals is not None:
            nm = _as_float_tensor("normals", self.normals, (H, W, 3), n)
            nm = torch.where(torch.isfinite(nm), nm, torch.zeros_like(nm))
            ln = nm.norm(dim=-1)
            bad = (ln > _UNIT_NORMAL_TOL) & ((ln - 1).abs() > _UNIT_NORMAL_TOL)
            if bool(bad.any()):
                _first_bad("normals (norm)", ln, bad, "unit length or 0")
            self.normals = nm.to(dev).contiguous()
        if self.bounds is not None:
            lo, hi = (_to_numpy64(b).reshape(-1) for b in self.bounds)
            if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
                raise ValueError(f"bounds must be two finite 3-vectors (lower, upper), got {self.bounds!r}")
            if np.any(hi <= lo):
                raise ValueError(f"bounds upper must exceed lower on every axis, got lower={lo.tolist()}, "
                                 f"upper={hi.tolist()}")
            self.bounds = (lo, hi)
        if self.points is not None:
            p = _to_numpy64(self.points)
            if p.ndim != 2 or p.shape[1] != 3:
                raise ValueError(f"points must have shape [P, 3], got {list(p.shape)}")
            if not np.all(np.isfinite(p)):
                idx = int(np.argwhere(~np.all(np.isfinite(p), axis=1))[0, 0])
                raise ValueError(f"points must be finite, got {p[idx].tolist()} at index {idx}")
            self.points = p
            if self.point_colors is not None:
                c = _to_numpy64(self.point_colors)
                if c.shape != p.shape:
                    raise ValueError(f"point_colors must have shape {list(p.shape)}, got {list(c.shape)}")
                if not np.all((c >= 0) & (c <= 1)):
                    raise ValueError(f"point_colors must be in [0, 1], got range [{c.min()}, {c.max()}]")
                self.point_colors = c
        elif self.point_colors is not None:
            raise ValueError("point_colors given without points")
        if self.background is not None:
            b = _to_numpy64(self.background).reshape(-1)
            if b.shape != (3,) or not np.all((b >= 0) & (b <= 1)):
                raise ValueError(f"background must be 3 floats in [0, 1] or None, got {self.background!r}")
            self.background = tuple(float(v) for v in b)
        for nm_ in ("train_indices", "test_indices"):
            v = getattr(self, nm_)
            if v is not None:
                a = np.asarray(v).reshape(-1)
                if a.size and (not np.issubdtype(a.dtype, np.integer) or a.min() < 0 or a.max() >= n):
                    raise ValueError(f"{nm_} must be integers in [0, {n - 1}], got {a.tolist()}")
                setattr(self, nm_, a.astype(np.int64))
        if self.gt_mesh is not None:
            import trimesh

            if not isinstance(self.gt_mesh, trimesh.Trimesh):
                raise TypeError(f"gt_mesh must be a trimesh.Trimesh, got {type(self.gt_mesh).__name__}")

    # -- basic properties ---------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return int(self.images.shape[2])

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return int(self.images.shape[1])

    @property
    def device(self) -> torch.device:
        """Device of the image tensors."""
        return self.images.device

    def require_views(self, n: int, purpose: str = "fitting") -> None:
        """Raise ``ValueError`` unless the scene has at least ``n`` cameras."""
        if len(self.cameras) < n:
            raise ValueError(f"{purpose} needs at least {n} cameras, got {len(self.cameras)}")

    def to(self, device) -> Scene:
        """The scene with its tensors on ``device``."""
        mv = {k: (getattr(self, k).to(device) if getattr(self, k) is not None else None)
              for k in ("images", "masks", "depths", "normals")}
        return self._replace(**mv)

    def _replace(self, **kw) -> Scene:
        return replace(self, **kw)

    # -- selection and resizing ---------------------------------------------------------------
    def subset(self, indices) -> Scene:
        """The scene restricted to the images ``indices`` (in that order); the train/test split is
        re-indexed to the kept images."""
        idx = np.asarray(indices).reshape(-1)
        n = len(self)
        if idx.size == 0 or not np.issubdtype(idx.dtype, np.integer) or idx.min() < -n or idx.max() >= n:
            raise ValueError(f"indices must be a non-empty list of integers in [0, {n - 1}], got {idx.tolist()}")
        idx = idx % len(self)
        ti = torch.as_tensor(idx, device=self.device)
        pos = {int(j): k for k, j in enumerate(idx)}

        def remap(split):
            if split is None:
                return None
            return np.array([pos[int(j)] for j in split if int(j) in pos], dtype=np.int64)

        return self._replace(
            cameras=[self.cameras[int(i)] for i in idx],
            images=self.images[ti],
            masks=None if self.masks is None else self.masks[ti],
            depths=None if self.depths is None else self.depths[ti],
            normals=None if self.normals is None else self.normals[ti],
            train_indices=remap(self.train_indices),
            test_indices=remap(self.test_indices),
        )

    def split(self, which: str = "train") -> Scene:
        """The ``"train"`` or ``"test"`` images as a scene (all images when no split is recorded)."""
        if which not in ("train", "test"):
            raise ValueError(f"which must be 'train' or 'test', got {which!r}")
        idx = self.train_indices if which == "train" else self.test_indices
        if idx is None:
            return self.subset(np.arange(len(self)))
        if len(idx) == 0:
            raise ValueError(f"scene {self.name!r} has no {which} images")
        return self.subset(idx)

    def downscaled(self, factor: float) -> Scene:
        """The scene with images resized by ``1 / factor`` (area averaging for colour, majority for
        masks, nearest for depth and normals) and intrinsics scaled to match."""
        f = float(factor)
        if not math.isfinite(f) or f < 1:
            raise ValueError(f"factor must be a finite number >= 1, got {factor!r}")
        if f == 1:
            return self._replace()
        cams = [c.scaled(1.0 / f) for c in self.cameras]
        h, w = cams[0].height, cams[0].width
        fn = torch.nn.functional
        img = fn.interpolate(self.images.permute(0, 3, 1, 2), size=(h, w), mode="area").permute(0, 2, 3, 1)
        masks = depths = normals = None
        if self.masks is not None:
            masks = fn.interpolate(self.masks[:, None].float(), size=(h, w), mode="area")[:, 0] >= 0.5
        if self.depths is not None:
            depths = fn.interpolate(self.depths[:, None], size=(h, w), mode="nearest-exact")[:, 0]
        if self.normals is not None:
            normals = fn.interpolate(self.normals.permute(0, 3, 1, 2), size=(h, w),
                                     mode="nearest-exact").permute(0, 2, 3, 1)
        return self._replace(cameras=cams, images=img.contiguous(), masks=masks, depths=depths, normals=normals)

    # -- frames ---------------------------------------------------------------------------------
    def transformed(self, sim: Similarity) -> Scene:
        """The scene seen through the similarity ``sim`` (cameras, depths, bounds, points, gt mesh)."""
        if not isinstance(sim, Similarity):
            raise TypeError(f"sim must be a wtopo.scene.Similarity, got {type(sim).__name__}")
        bounds = None
        if self.bounds is not None:
            bounds = (sim.to_internal(self.bounds[0]), sim.to_internal(self.bounds[1]))
        info = dict(self.info)
        if "region_of_interest" in info:  # an internal-frame box travels with the frame
            info["region_of_interest"] = tuple(sim.to_internal(b) for b in info["region_of_interest"])
        return self._replace(
            cameras=[sim.to_internal(c) for c in self.cameras],
            depths=None if self.depths is None else self.depths * float(sim.scale),
            bounds=bounds,
            points=None if self.points is None else sim.to_internal(self.points),
            gt_mesh=None if self.gt_mesh is None else sim.to_internal(self.gt_mesh),
            info=info,
        )

    def normalization(self, *, margin: float = NORMALIZATION_MARGIN) -> Similarity:
        """The similarity mapping the region of interest into ``[margin, 1 - margin]^3`` (centred,
        longest side fills it).

        The region of interest is, in order of preference: ``bounds``; the visual hull of the
        masks; the points seen by at least half of the cameras (2nd-98th percentile box); the
        region inside at least 90 % of the camera frusta. The ground-truth mesh is never used.
        The estimate is equivariant under similarities of the input (float64 throughout), so a
        scene scaled by 1e-3 or moved by 1e4 normalises to the same internal scene.

        Args:
            margin: empty border on every side of the unit cube, in [0, 0.5).

        Raises:
            ValueError: the region must come from the cameras but they are fewer than two,
                coincide, or lie on one line; no region could be found.
        """
        m = float(margin)
        if not (0 <= m < 0.5):
            raise ValueError(f"margin must be in [0, 0.5), got {margin!r}")
        if m not in self._norm_cache:
            lo, hi = self.region_of_interest()
            ext = float(np.max(hi - lo))
            scale = (1.0 - 2.0 * m) / ext
            center = 0.5 * (lo + hi)
            self._norm_cache[m] = Similarity(scale, tuple(0.5 / scale - center))
        return self._norm_cache[m]

    def normalized(self, *, margin: float = NORMALIZATION_MARGIN) -> Scene:
        """The scene in the internal frame of :meth:`normalization`; its ``info["normalization"]``
        holds that :class:`Similarity`, whose :meth:`~Similarity.to_world` maps results back, and
        ``info["region_of_interest"]`` the region it fitted, ``(lower [3], upper [3])`` internal units."""
        sim = self.normalization(margin=margin)
        out = self.transformed(sim)
        lo, hi = self.region_of_interest()
        out.info = {**out.info, "normalization": sim, "region_of_interest": (sim.to_internal(lo), sim.to_internal(hi))}
        return out

    def region_of_interest(self) -> tuple[np.ndarray, np.ndarray]:
        """The world-frame box ``(lower [3], upper [3])`` (float64) that :meth:`normalization` fits
        (estimated once per scene)."""
        if not self._roi_cache:
            self._roi_cache.append(self._estimate_region())
        lo, hi = self._roi_cache[0]
        return lo.copy(), hi.copy()

    def _estimate_region(self) -> tuple[np.ndarray, np.ndarray]:
        if self.bounds is not None:
            return self.bounds[0], self.bounds[1]
        if self.masks is not None:
            return visual_hull_box(self.cameras, self.masks)
        if self.points is not None and len(self.points) >= 8:
            box = points_box(self.cameras, self.points)
            if box is not None:
                return box
        return visual_hull_box(self.cameras, None, self.images)

    # -- output ---------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write the scene in Blender / NeRF-synthetic format (``transforms_train.json``,
        ``transforms_test.json``, RGBA PNGs; alpha = mask) plus ``gt_mesh.ply`` when present, so
        :func:`wtopo.load_scene` reads it back. Non-centred or anisotropic intrinsics are written
        as per-frame ``fl_x, fl_y, cx, cy`` beside ``camera_angle_x``."""
        from .loaders._blender_write import write_blender

        write_blender(self, path)
