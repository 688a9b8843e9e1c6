# SPDX-License-Identifier: Apache-2.0
"""What a synthetic scene's pixels show besides the mesh, and how hits are shaded: scikit-image
textures in triplanar or spherical projection, fixed world-frame lights, an inward-facing room, the
unbounded environment (ground, ring of hills, cloudy sky at infinity) and the per-camera shading of
ray-cast hits (:func:`_shade`)."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

TEXTURES = ("astronaut", "coffee", "rocket", "chelsea", "colorwheel", "brick", "gravel", "grass", "camera", "flat")
_FLAT_ALBEDO = 0.7  # texture="flat": one grey albedo, so only the shading tells the shape


_AMBIENT = 0.3  # light reaching faces turned away from both lights (keeps their texture visible)
_LIGHTS = ((0.55, 0.95, 0.35), (0.35, -0.25, -0.8))  # (right, up, front) directions of key and fill light
_LIGHT_POWER = (0.55, 0.25)  # key + fill + ambient = 1.1: lit faces reach the texture's full range


_TEXTURE_TILES = 1.5  # texture repeats per object diameter in the triplanar mapping


# -- the unbounded environment (``background="environment"``); lengths in object radii -------------
_ENV_GROUND_HALF = 40.0  # ground half-size: 30-50x the object radius (unbounded-scene tests), far past any camera
_ENV_GROUND_CELLS = 64  # ground quads per side (1.25 radii each): a region-of-interest crop of the
#                         ground then rejects few area samples in the evaluation
_ENV_HILL_FEET = (12.0, 20.0)  # inner and outer foot radius of the ring of hills (10-20 radii)
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
