# SPDX-License-Identifier: Apache-2.0
"""Synthetic scenes rendered from triangle meshes, and the embedded default scenes.

:func:`from_mesh` casts one ray per pixel against the mesh (:func:`wtopo.ops.raycast_mesh`) from a
camera rig around it, and shades the hits: albedo from a scikit-image picture mapped by a
triplanar or spherical projection, Lambertian shading under fixed world-frame lights (so colours
do not depend on the viewpoint), optional textured floor and walls, or an unbounded environment
(a large ground, a ring of hills and a sky at infinity), with optional photometric noise and
per-image exposure changes (:class:`Photometric`). It returns a :class:`wtopo.Scene` with colour,
z-depth, camera-facing normals, object masks and the mesh as ``gt_mesh``, all in the mesh's own
frame.

:func:`load` gives the named defaults: ``"bunny"`` (the Stanford bunny shipped in Warp's example
assets, sized for a 2-core CPU fit), ``"bunny_room"`` (the same bunny in a textured room, no masks),
``"bunny_env"`` / ``"bunny_env_forward"`` (the bunny on the ground of an unbounded environment, from
a 360 orbit and from a forward-facing rig, noisy, varying exposure: the real-capture benchmarks)
and ``"sphere"`` (a tiny icosphere for tests).
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from .camera import Camera

__all__ = ["from_mesh", "load", "names", "bunny_mesh", "rig_cameras", "Photometric", "RIGS", "TEXTURES",
           "ROI_HORIZONTAL_GROWTH"]

RIGS = ("sphere", "hemisphere", "orbit", "forward")
TEXTURES = ("astronaut", "coffee", "rocket", "chelsea", "colorwheel", "brick", "gravel", "grass", "camera", "flat")
_FLAT_ALBEDO = 0.7  # texture="flat": one grey albedo, so only the shading tells the shape
_BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
_AMBIENT = 0.3  # light reaching faces turned away from both lights (keeps their texture visible)
_LIGHTS = ((0.55, 0.95, 0.35), (0.35, -0.25, -0.8))  # (right, up, front) directions of key and fill light
_LIGHT_POWER = (0.55, 0.25)  # key + fill + ambient = 1.1: lit faces reach the texture's full range
_FIT_MARGIN = 1.15  # camera distance keeps the bounding sphere this much inside the narrower field of view
_TEXTURE_TILES = 1.5  # texture repeats per object diameter in the triplanar mapping
_ORBIT_ELEVATION = 25.0  # degrees: the orbit rig's default ring sees the top and the sides of an object

# -- the unbounded environment (``background="environment"``); lengths in object radii -------------
_ENV_GROUND_HALF = 40.0  # ground half-size: 30-50x the object radius (issue 13), far past any camera
_ENV_GROUND_CELLS = 64  # ground quads per side (1.25 radii each): a region-of-interest crop of the
#                         ground then rejects few area samples in the evaluation
_ENV_HILL_FEET = (12.0, 20.0)  # inner and outer foot radius of the ring of hills (10-20 radii, issue 13)
_ENV_HILL_HEIGHT = (1.5, 4.0)  # ridge height range: tops 5-15 degrees above the horizon from the rigs
_ENV_HILL_SEGMENTS = 128  # segments around the ring (2.8 degrees each: smooth at 160 px)
_ENV_HILL_PROFILE = ((0.0, 0.0), (0.25, 0.6), (0.5, 1.0), (0.75, 0.6), (1.0, 0.0))  # (radial, height) fractions
_ENV_HILL_WAVES = 4  # random sinusoids along the ring shaping the ridge heights
_ENV_GROUND_PERIOD = 1.0  # ground texture period (radii): gravel grains visible near the object
_ENV_HILL_PERIOD = 4.0  # hill texture period (radii): far away, coarse
_ENV_CAMERA_CLEARANCE = 0.25  # every camera centre at least this high above the ground
_ENV_SUPERSAMPLE = 2  # colour rays per pixel side, area-averaged: textures far away do not alias
_ENV_DEFAULT_FOV = 1.0  # radians (57 degrees): the horizon is visible from the orbit rig below
_ENV_ORBIT_ELEVATION = 15.0  # degrees: with _ENV_DEFAULT_FOV the top of every orbit image shows the sky
_SKY_HORIZON = np.array([0.85, 0.87, 0.90])  # sky colour at the horizon (hazy)
_SKY_ZENITH = np.array([0.30, 0.50, 0.85])  # sky colour straight up
_SKY_CLOUD = np.array([0.97, 0.97, 0.97])
_SKY_CLOUD_SCALE = 3.0  # cloud noise lattice cells per unit of direction: a few clouds per view
_SKY_CLOUD_LATTICE = 16  # random lattice side of the cloud noise (wraps; 16 cells > 2 * scale + 2)
_SKY_CLOUD_COVER = (0.45, 0.70)  # noise values between which clouds fade in (about a third of the sky)
_SKY_GROUND_DIM = 0.8  # rays below the horizon that miss everything see the horizon colour dimmed

# The region of interest recorded in ``info["roi"]``: the object's bounding box with its horizontal
# sides grown by this factor (the ground around the object's foot, seen by every view, belongs to
# the reconstruction), from _ROI_BELOW object heights under the ground (so the ground plane lies
# strictly inside the box, not on a face of it where a crop is ambiguous) to _ROI_ABOVE over the top.
ROI_HORIZONTAL_GROWTH = 1.5
_ROI_BELOW = 0.05
_ROI_ABOVE = 0.10


@functools.cache
def _texture(name: str) -> np.ndarray:
    import skimage.data

    if name not in TEXTURES:
        raise ValueError(f"texture must be one of {TEXTURES} (scikit-image's bundled images or 'flat'), got {name!r}")
    if name == "flat":
        return np.full((1, 1, 3), _FLAT_ALBEDO, np.float32)
    a = np.asarray(getattr(skimage.data, name)(), dtype=np.float32) / 255.0
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return np.ascontiguousarray(a[..., :3])


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around; (u, v) in texture periods, v down the image."""
    h, w = tex.shape[:2]
    x = np.mod(u, 1.0) * w - 0.5
    y = np.mod(v, 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0, x1, y1 = x0 % w, y0 % h, (x0 + 1) % w, (y0 + 1) % h
    return ((tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx) * (1 - fy)
            + (tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx) * fy)


def _triplanar(tex, p, n, period, offset):
    q = p / period + offset
    w = np.abs(n) ** 4
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    return (w[:, :1] * _sample(tex, q[:, 1], q[:, 2]) + w[:, 1:2] * _sample(tex, q[:, 0], q[:, 2])
            + w[:, 2:] * _sample(tex, q[:, 0], q[:, 1]))


def _spherical(tex, p, center, frame, offset):
    d = (p - center) @ frame.T  # (right, up, front) coordinates
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    lon = np.arctan2(d[:, 0], d[:, 2]) / (2 * math.pi) + 0.5
    lat = np.arccos(np.clip(d[:, 1], -1, 1)) / math.pi
    return _sample(tex, lon + offset[0], lat)


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


def _room(center, radius, frame, floor_level, half):
    """Inward-facing box: floor at ``floor_level`` along up, walls at ``half`` from the centre."""
    r, u, f = frame
    base = center + (floor_level - center @ u) * u
    corners = []
    for du in (0.0, 2.0 * half):
        for dr, df in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            corners.append(base + du * u + half * (dr * r + df * f))
    v = np.array(corners)
    quads = [(0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (1, 5, 6, 2), (2, 6, 7, 3), (3, 7, 4, 0)]
    faces = []
    for a, b, c_, d in quads:
        faces += [(a, b, c_), (a, c_, d)]
    return v, np.array(faces, dtype=np.int64)


def _grid_faces(rows: int, cols: int, closed: bool = False) -> np.ndarray:
    """Two triangles per cell of a (rows x cols) vertex grid, row-major; ``closed`` wraps the rows."""
    r_end = rows if closed else rows - 1
    i, j = np.meshgrid(np.arange(r_end), np.arange(cols - 1), indexing="ij")
    a = i * cols + j
    b = ((i + 1) % rows) * cols + j
    a, b = a.reshape(-1), b.reshape(-1)
    return np.concatenate([np.stack([a, b, b + 1], 1), np.stack([a, b + 1, a + 1], 1)]).astype(np.int64)


def _environment(center, radius, frame, floor_level, rng):
    """Ground (a tessellated square) and a ring of hills standing on it.

    Returns ``(verts [V, 3], faces [F, 3], n_ground_faces)``, world units; ground faces come first.
    """
    r, u, f = frame
    base = center + (floor_level - center @ u) * u
    g = np.linspace(-_ENV_GROUND_HALF, _ENV_GROUND_HALF, _ENV_GROUND_CELLS + 1) * radius
    gr, gf = np.meshgrid(g, g, indexing="ij")
    ground_v = base + gr.reshape(-1, 1) * r + gf.reshape(-1, 1) * f
    ground_f = _grid_faces(len(g), len(g))
    theta = np.arange(_ENV_HILL_SEGMENTS) * (2 * math.pi / _ENV_HILL_SEGMENTS)
    ridge = np.zeros_like(theta)
    for k in range(1, _ENV_HILL_WAVES + 1):  # smooth random ridge line, periodic around the ring
        ridge += rng.uniform(0.5, 1.0) / k * np.sin(k * theta + rng.uniform(0, 2 * math.pi))
    ridge = (ridge - ridge.min()) / max(ridge.max() - ridge.min(), 1e-12)
    height = (_ENV_HILL_HEIGHT[0] + (_ENV_HILL_HEIGHT[1] - _ENV_HILL_HEIGHT[0]) * ridge) * radius
    inner, outer = (x * radius for x in _ENV_HILL_FEET)
    prof = np.asarray(_ENV_HILL_PROFILE)
    rad = inner + (outer - inner) * prof[:, 0]  # [P]
    hv = (base + (rad[None, :, None] * (np.cos(theta)[:, None, None] * r + np.sin(theta)[:, None, None] * f))
          + (height[:, None] * prof[None, :, 1])[..., None] * u)
    hill_f = _grid_faces(len(theta), len(prof), closed=True)
    verts = np.concatenate([ground_v, hv.reshape(-1, 3)])
    faces = np.concatenate([ground_f, hill_f + len(ground_v)])
    return verts, faces, len(ground_f)


def _cloud_noise(d: np.ndarray, lattice: np.ndarray) -> np.ndarray:
    """Two-octave smooth value noise in [0, 1] of unit directions ``d`` [M, 3] (direction only)."""
    n = lattice.shape[0]
    out = np.zeros(len(d))
    for octave, amp in ((1.0, 0.65), (2.0, 0.35)):
        q = (d * _SKY_CLOUD_SCALE * octave + n / 2) % n
        i0 = np.floor(q).astype(np.int64)
        t = q - i0
        t = t * t * (3 - 2 * t)  # smoothstep: no lattice creases
        acc = 0.0
        for corner in range(8):
            o = np.array([(corner >> k) & 1 for k in range(3)])
            w = np.prod(np.where(o, t, 1 - t), axis=1)
            idx = (i0 + o) % n
            acc = acc + w * lattice[idx[:, 0], idx[:, 1], idx[:, 2]]
        out += amp * acc
    return out


def _sky(d: np.ndarray, up: np.ndarray, lattice: np.ndarray) -> np.ndarray:
    """Sky colour [M, 3] of world ray directions ``d`` [M, 3]: a horizon-to-zenith gradient with
    clouds; it depends on the direction only (a sky at infinity)."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = d @ up
    t = np.sqrt(np.clip(e, 0, 1))[:, None]
    col = _SKY_HORIZON * (1 - t) + _SKY_ZENITH * t
    lo, hi = _SKY_CLOUD_COVER
    c = np.clip((_cloud_noise(d, lattice) - lo) / (hi - lo), 0, 1)
    c = (c * c * (3 - 2 * c) * np.clip(e / 0.05, 0, 1))[:, None]  # clouds fade out at the horizon
    col = col * (1 - c) + _SKY_CLOUD * c
    return np.where((e < 0)[:, None], _SKY_HORIZON * _SKY_GROUND_DIM, col)


@dataclass(frozen=True, kw_only=True)
class Photometric:
    """Camera imperfections applied to the training images of a synthetic scene (held-out views
    stay clean: they are the reference a perfect fit reproduces).

    Deterministic given the scene's seed. Applied as ``clip(gain * wb * image + N(0, noise^2))``.
    """

    noise: float = 0.0
    """Standard deviation of additive Gaussian pixel noise, per channel, in [0, 1] intensity units."""
    exposure: float = 0.0
    """Half-range of a uniform random gain per image: gains in ``[1 - exposure, 1 + exposure]``."""
    white_balance: float = 0.0
    """Half-range of a uniform random extra gain per image and channel (white-balance change)."""

    def __post_init__(self):
        for k in ("noise", "exposure", "white_balance"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 <= v < 1):
                raise ValueError(f"Photometric.{k} must be a number in [0, 1), got {v!r}")


def _shade(caster, cam, vt, ft, kinds, ctx):
    """Ray cast one camera with ``caster`` (a :class:`wtopo.raycast.MeshRaycaster`) and shade it:
    ``(image [H, W, 3], depth [H, W], normal [H, W, 3], object mask [H, W])`` as float64 / bool
    numpy arrays."""
    r = caster.raycast(vt, ft, cam)
    hit = r.mask.numpy()
    fid = r.face_id.numpy()[hit].astype(np.int64)
    o, d = (x.numpy().astype(np.float64) for x in cam.pixel_rays("cpu", torch.float64))
    z = r.depth.numpy().astype(np.float64)[hit]
    p = o[hit] + z[:, None] * d[hit]
    nrm = r.normal.numpy().astype(np.float64)[hit]
    facing = np.einsum("ij,ij->i", nrm, d[hit]) > 0
    nrm[facing] *= -1  # towards the camera
    kind = kinds[fid]
    alb = np.zeros((len(p), 3))
    for k, (tex, period, tint) in ctx["materials"].items():
        sel = kind == k
        if not sel.any():
            continue
        if period is None:  # the object's own mapping
            if ctx["mapping"] == "triplanar":
                alb[sel] = _triplanar(tex, p[sel] - ctx["center"], nrm[sel], 2 * ctx["radius"] / _TEXTURE_TILES,
                                      ctx["offset"])
            else:
                alb[sel] = _spherical(tex, p[sel], ctx["center"], ctx["frame"], ctx["offset"])
        else:
            alb[sel] = _triplanar(tex, p[sel] - ctx["center"], nrm[sel], period, ctx["offset"]) * tint
    shade = _AMBIENT + sum(pw * np.clip(nrm @ ld, 0, None) for pw, ld in zip(_LIGHT_POWER, ctx["lights"]))
    H, W = cam.height, cam.width
    img = np.empty((H, W, 3))
    if ctx["sky"] is not None:
        img[~hit] = _sky(d[~hit], ctx["frame"][1], ctx["sky"])
    else:
        img[:] = ctx["bg"]
    img[hit] = alb * shade[:, None]
    depth = np.zeros((H, W))
    depth[hit] = z
    normal = np.zeros((H, W, 3))
    normal[hit] = nrm
    mask = np.zeros((H, W), bool)
    mask[hit] = kind == _OBJECT
    return np.clip(img, 0, 1), depth, normal, mask


_OBJECT, _FLOOR, _WALL, _HILL = 0, 1, 2, 3  # face kinds (material index) of a synthetic scene
_SCENERIES = ("room", "ground", "environment")


def _roi_box(used: np.ndarray, frame: np.ndarray, floor_level: float) -> tuple[list, list]:
    """World axis-aligned box around the object's region of interest (see ROI_HORIZONTAL_GROWTH)."""
    q = used @ frame.T  # (right, up, front) coordinates
    lo, hi = q.min(0), q.max(0)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    height = hi[1] - floor_level
    lo2, hi2 = mid - ROI_HORIZONTAL_GROWTH * half, mid + ROI_HORIZONTAL_GROWTH * half
    lo2[1], hi2[1] = floor_level - _ROI_BELOW * height, hi[1] + _ROI_ABOVE * height
    corners = np.array([[(lo2, hi2)[(k >> a) & 1][a] for a in range(3)] for k in range(8)]) @ frame
    return corners.min(0).tolist(), corners.max(0).tolist()


def from_mesh(mesh, *, n_views: int = 32, resolution=128, rig: str = "sphere", texture: str = "astronaut",
              background="black", seed: int = 0, mapping: str = "triplanar", up=(0, 0, 1), fov: float | None = None,
              n_test: int = 0, name: str = "mesh", elevation: float | None = None,
              photometric: Photometric | None = None, bounds_from_roi: bool = False, cameras=None):
    """Render a synthetic scene of a triangle mesh.

    Args:
        mesh: ``trimesh.Trimesh`` or ``(verts [V, 3], faces [F, 3])``; kept as ``gt_mesh``, in its frame.
        n_views: training views.
        resolution: image size, ``int`` or ``(width, height)``.
        rig: camera rig (see :func:`rig_cameras`).
        texture: scikit-image picture used as the object's albedo (see :data:`TEXTURES`), or
            ``"flat"``: one grey albedo (0.7), so that only the Lambertian shading shows the shape.
        background: ``"black"``, ``"white"`` or 3 floats (constant; masks are returned), or
            ``"room"`` (textured floor, walls and ceiling; no masks) or ``"ground"`` (a textured
            floor under the object, constant black elsewhere; no masks): for these only the object
            is ``gt_mesh``. ``"environment"``: an unbounded outdoor scene, the object on a textured
            ground 80 object radii wide, a ring of textured hills 12-20 radii away and a sky at
            infinity (colour by ray direction: gradient and clouds; depth 0) where rays hit
            nothing; no masks, and ``gt_mesh`` is all geometry (object, ground, hills), so its
            crop to the region of interest ``info["roi"]`` is the ground truth there. Colours are
            area-averaged over 2 x 2 rays per pixel; depths and normals are the pixel-centre ray's.
        seed: rig rotation, texture offset, hills, clouds and photometric draws (the scene is
            deterministic given it).
        mapping: ``"triplanar"`` or ``"spherical"`` texture projection.
        up: world up direction (floor, lights and rigs use it).
        fov: field of view of the narrower image side, radians (default 0.7; 1.0 for the
            environment, whose orbit images then show the horizon).
        n_test: extra held-out views (another rotation of the same rig) appended after the
            training views and listed in ``test_indices``.
        name: scene name.
        elevation: orbit ring elevation in degrees (default 25; 15 for the environment).
        photometric: noise, exposure and white-balance changes of the training images
            (:class:`Photometric`); the per-image gains [N, 3] are recorded in ``info["gains"]``.
        bounds_from_roi: with a scenery background, set ``Scene.bounds`` to ``info["roi"]`` (as
            datasets that ship a bounding box do: DTU ``scale_mat``, nerfstudio ``aabb``); by
            default the fit must find the region of interest itself.
        cameras: render from these :class:`~wtopo.Camera` s (one size) instead of a rig: ``n_views``
            becomes their count and ``rig``, ``n_test`` and ``elevation`` are not used (large scenes
            with several camera segments, :func:`wtopo.chunks.street_scene`).

    Returns:
        :class:`wtopo.Scene` with images, depths (z-depth, 0 on misses), camera-facing normals,
        masks (constant backgrounds only), ``gt_mesh`` and ``background``. With a scenery
        background ``info["roi"]`` holds the region of interest ``(lower [3], upper [3])``: the
        object's bounding box, its horizontal sides grown by :data:`ROI_HORIZONTAL_GROWTH`,
        from just under the ground to just over the object.
    """
    import trimesh

    from .raycast import MeshRaycaster
    from .scene import Scene

    if isinstance(mesh, trimesh.Trimesh):
        verts, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    else:
        verts, faces = (np.asarray(a) for a in mesh)
        verts, faces = verts.astype(np.float64), faces.astype(np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) == 0:
        raise ValueError(f"mesh vertices must have shape [V>0, 3], got {list(verts.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh faces must have shape [F>0, 3], got {list(faces.shape)}")
    if mapping not in ("triplanar", "spherical"):
        raise ValueError(f"mapping must be 'triplanar' or 'spherical', got {mapping!r}")
    scenery = background if isinstance(background, str) and background in _SCENERIES else None
    bg = None
    if scenery is None:
        bg = _BACKGROUNDS.get(background) if isinstance(background, str) else background
        if bg is None or np.asarray(bg, dtype=np.float64).shape != (3,):
            raise ValueError(f"background must be 'black', 'white', 3 floats, {', '.join(map(repr, _SCENERIES))}, "
                             f"got {background!r}")
        bg = tuple(float(x) for x in bg)
    elif rig == "sphere" and cameras is None:
        raise ValueError(f"background={background!r} puts a floor under the object: use rig 'hemisphere', "
                         "'orbit' or 'forward', got 'sphere'")
    if bounds_from_roi and scenery is None:
        raise ValueError(f"bounds_from_roi needs a scenery background {_SCENERIES}, got {background!r}")
    if isinstance(n_test, bool) or int(n_test) != n_test or n_test < 0:
        raise ValueError(f"n_test must be an integer >= 0, got {n_test!r}")
    if photometric is not None and not isinstance(photometric, Photometric):
        raise TypeError(f"photometric must be a wtopo.scenes.Photometric or None, got {type(photometric).__name__}")
    env = scenery == "environment"
    if fov is None:
        fov = _ENV_DEFAULT_FOV if env else 0.7
    if elevation is None:
        elevation = _ENV_ORBIT_ELEVATION if env else _ORBIT_ELEVATION

    frame = _frame_from_up(up)
    used = verts[np.unique(faces)]
    center = 0.5 * (used.min(0) + used.max(0))
    radius = float(np.linalg.norm(used - center, axis=1).max())
    floor = float((used @ frame[1]).min())

    def rig_at(c):
        cams = rig_cameras(rig, n_views, c, radius, resolution=resolution, up=frame[1], fov=fov, seed=seed,
                           elevation=elevation)
        if n_test:
            cams += [replace_name(cm, f"test_{k:03d}") for k, cm in enumerate(
                rig_cameras(rig, n_test, c, radius, resolution=resolution, up=frame[1], fov=fov, seed=seed + 7919,
                            elevation=elevation))]
        return cams

    if cameras is not None:
        cams = list(cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise TypeError("cameras must be a non-empty list of wtopo.Camera or None")
        n_views, n_test = len(cams), 0
    else:
        cams = rig_at(center)
    if env and cameras is None:  # lift the rig so that every camera stands above the ground
        low = min(float(cm.center @ frame[1]) for cm in cams) - floor
        lift = _ENV_CAMERA_CLEARANCE * radius - low
        if lift > 0:
            cams = rig_at(center + lift * frame[1])

    rng = np.random.default_rng(seed)
    offset = rng.uniform(0, 1, size=3)
    all_v, all_f = verts, faces
    kinds = np.zeros(len(faces), np.int64)
    if scenery in ("room", "ground"):
        dist = max(float(np.linalg.norm(c.center - center)) for c in cams)
        rv, rf = _room(center, radius, frame, floor, 1.5 * dist)
        if scenery == "ground":
            rf = rf[:2]
        rk = np.full(len(rf), _WALL)
        rk[:2] = _FLOOR
    elif env:
        rv, rf, n_ground = _environment(center, radius, frame, floor, rng)
        rk = np.full(len(rf), _HILL)
        rk[:n_ground] = _FLOOR
    if scenery is not None:
        all_v = np.concatenate([verts, rv])
        all_f = np.concatenate([faces, rf + len(verts)])
        kinds = np.concatenate([kinds, rk])

    lights = [np.asarray(d) @ frame for d in _LIGHTS]
    ctx = {
        "center": center, "radius": radius, "frame": frame, "offset": offset, "mapping": mapping, "bg": bg,
        "lights": [d / np.linalg.norm(d) for d in lights],
        "materials": {  # kind -> (texture, period or None for the object's mapping, tint)
            _OBJECT: (_texture(texture), None, None),
            _FLOOR: (_texture("gravel"), (_ENV_GROUND_PERIOD if env else 1.0) * radius, np.array([0.75, 0.7, 0.6])),
            _WALL: (_texture("brick"), radius, np.array([0.9, 0.55, 0.45])),  # sand floor, reddish brick walls
            _HILL: (_texture("grass"), _ENV_HILL_PERIOD * radius, np.array([0.8, 0.95, 0.7])),
        },
        "sky": rng.random((_SKY_CLOUD_LATTICE,) * 3) if env else None,
    }
    if scenery is not None and not env:
        ctx["bg"] = (0.0, 0.0, 0.0)

    vt = torch.as_tensor(all_v, dtype=torch.float32)
    ft = torch.as_tensor(all_f, dtype=torch.int32)
    n = len(cams)
    H, W = cams[0].height, cams[0].width
    images = np.zeros((n, H, W, 3), np.float32)
    depths = np.zeros((n, H, W), np.float32)
    normals = np.zeros((n, H, W, 3), np.float32)
    masks = np.zeros((n, H, W), bool)
    # One BVH for all views. The environment's 5 rays per pixel use the per-ray query, 3-4x faster
    # than the watertight packet sweep on its long grazing rays; on 4 views at 320 x 240 the two
    # differed in 1 face id of 307k rays and in no hit/miss.
    caster = MeshRaycaster(conservative=not env)
    with torch.no_grad():
        for i, cam in enumerate(cams):
            img, depths[i], normals[i], masks[i] = _shade(caster, cam, vt, ft, kinds, ctx)
            if env:
                s = _ENV_SUPERSAMPLE
                fine = _shade(caster, cam.scaled(s), vt, ft, kinds, ctx)[0]
                img = fine.reshape(H, s, W, s, 3).mean(axis=(1, 3))
            images[i] = img

    info = {"rig": rig, "texture": texture, "mapping": mapping, "seed": seed, "up": frame[1].tolist()}
    if photometric is not None:
        prng = np.random.default_rng([seed, 1])  # its own stream: the geometry does not depend on it
        gain = prng.uniform(1 - photometric.exposure, 1 + photometric.exposure, (n_views, 1))
        gains = gain * prng.uniform(1 - photometric.white_balance, 1 + photometric.white_balance, (n_views, 3))
        noise = prng.normal(0.0, photometric.noise, images[:n_views].shape) if photometric.noise else 0.0
        images[:n_views] = np.clip(images[:n_views] * gains[:, None, None, :].astype(np.float32) + noise, 0, 1)
        info["gains"] = gains.tolist()
        info["photometric"] = dict(noise=photometric.noise, exposure=photometric.exposure,
                                   white_balance=photometric.white_balance)
    bounds = None
    if scenery is not None:
        info["roi"] = _roi_box(used, frame, floor)
        if bounds_from_roi:
            bounds = tuple(np.asarray(b) for b in info["roi"])
    if env:
        gt = trimesh.Trimesh(all_v, all_f, process=False)
        info["background"] = "environment"
    else:
        gt = trimesh.Trimesh(verts, faces, process=False)
    split = {}
    if n_test:
        split = dict(train_indices=np.arange(n_views), test_indices=np.arange(n_views, n))
    return Scene(cams, images, masks=masks if scenery is None else None, depths=depths, normals=normals,
                 gt_mesh=gt, background=bg, bounds=bounds, name=name, info=info, **split)


def replace_name(camera: Camera, name: str) -> Camera:
    """The same camera under another name."""
    return Camera(camera.K, camera.world_to_camera, camera.width, camera.height, camera.distortion, name)


@functools.lru_cache(maxsize=1)
def _bunny_arrays():
    import warp.examples
    from pxr import Usd, UsdGeom

    path = os.path.join(warp.examples.get_asset_directory(), "bunny.usd")
    stage = Usd.Stage.Open(path)
    if stage is None:
        raise FileNotFoundError(f"cannot open the bunny asset {path}")
    prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
    if prim is None:
        raise ValueError(f"{path} holds no mesh")
    usd_mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(usd_mesh.GetPointsAttr().Get(), dtype=np.float64)
    counts = np.asarray(usd_mesh.GetFaceVertexCountsAttr().Get())
    idx = np.asarray(usd_mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default()), dtype=np.float64)
    pts = pts @ xf[:3, :3] + xf[3, :3]  # USD matrices are row-vector convention
    # fan-triangulate polygons (the asset is all triangles; this keeps other assets usable)
    tris, start = [], 0
    for c in counts:
        for k in range(1, c - 1):
            tris.append((idx[start], idx[start + k], idx[start + k + 1]))
        start += c
    up = UsdGeom.GetStageUpAxis(stage)
    return pts, np.asarray(tris, dtype=np.int64), up


def bunny_mesh():
    """The Stanford bunny from Warp's example assets (``bunny.usd``, parsed once per process) and
    the stage's up axis as a vector: ``(trimesh.Trimesh, up [3])``."""
    import trimesh

    pts, tris, up = _bunny_arrays()
    upv = {"Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}[str(up)]
    return trimesh.Trimesh(pts.copy(), tris.copy(), process=False), upv


_DEFAULTS = {
    "bunny": dict(n_views=32, resolution=128, rig="sphere", texture="astronaut", background="black"),
    "bunny_room": dict(n_views=32, resolution=128, rig="hemisphere", texture="astronaut", background="room"),
    "bunny_env": dict(n_views=48, resolution=(160, 120), rig="orbit", texture="astronaut", background="environment",
                      n_test=8, photometric=Photometric(noise=0.01, exposure=0.1, white_balance=0.03)),
    "bunny_env_forward": dict(n_views=48, resolution=(160, 120), rig="forward", texture="astronaut",
                              background="environment", n_test=8,
                              photometric=Photometric(noise=0.01, exposure=0.1, white_balance=0.03)),
    "sphere": dict(n_views=12, resolution=40, rig="sphere", texture="coffee", background="black"),
}


def names() -> tuple[str, ...]:
    """Names accepted by :func:`load`."""
    return tuple(_DEFAULTS)


def load(name: str = "bunny", **overrides):
    """An embedded default scene.

    Args:
        name: ``"bunny"`` (32 views of 128 px over the full sphere, masks, black background),
            ``"bunny_room"`` (32 views of 128 px from the upper hemisphere inside a textured room,
            no masks), ``"bunny_env"`` (48 + 8 held-out views of 160 x 120 px from a 360 orbit at 15
            degrees elevation, the bunny on the ground of the unbounded environment, 1 % pixel noise,
            +-10 % exposure and +-3 % white balance per training image, no masks),
            ``"bunny_env_forward"`` (the same from a forward-facing 7 x 7 grid, LLFF-like) or
            ``"sphere"`` (12 views of 40 px of a radius-1 icosphere, for tests). A tiny unbounded
            scene for tests: ``load("bunny_env", n_views=12, resolution=48, n_test=2)``.
        **overrides: any :func:`from_mesh` keyword (``n_views``, ``resolution``, ``seed``, ...).
    """
    import trimesh

    if name not in _DEFAULTS:
        raise ValueError(f"name must be one of {names()}, got {name!r}")
    kw = {**_DEFAULTS[name], "name": name, **overrides}
    if name == "sphere":
        mesh, up = trimesh.creation.icosphere(subdivisions=3, radius=1.0), (0.0, 0.0, 1.0)
    else:
        mesh, up = bunny_mesh()
    kw.setdefault("up", up)
    return from_mesh(mesh, **kw)
