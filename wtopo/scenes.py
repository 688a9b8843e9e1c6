# SPDX-License-Identifier: Apache-2.0
"""Synthetic scenes rendered from triangle meshes, and the embedded default scenes.

:func:`from_mesh` casts one ray per pixel against the mesh (:func:`wtopo.ops.raycast_mesh`) from a
camera rig around it, and shades the hits: albedo from a scikit-image picture mapped by a
triplanar or spherical projection, Lambertian shading under fixed world-frame lights (so colours
do not depend on the viewpoint), optional textured floor and walls. It returns a
:class:`wtopo.Scene` with colour, z-depth, camera-facing normals, object masks and the mesh as
``gt_mesh``, all in the mesh's own frame.

:func:`load` gives the named defaults: ``"bunny"`` (the Stanford bunny shipped in Warp's example
assets, sized for a 2-core CPU fit), ``"bunny_room"`` (the same bunny in a textured room, no masks)
and ``"sphere"`` (a tiny icosphere for tests).
"""

from __future__ import annotations

import functools
import math
import os

import numpy as np
import torch

from .camera import Camera

__all__ = ["from_mesh", "load", "names", "bunny_mesh", "rig_cameras", "RIGS", "TEXTURES"]

RIGS = ("sphere", "hemisphere", "orbit", "forward")
TEXTURES = ("astronaut", "coffee", "rocket", "chelsea", "colorwheel", "brick", "gravel", "grass", "camera")
_BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
_AMBIENT = 0.3  # light reaching faces turned away from both lights (keeps their texture visible)
_LIGHTS = ((0.55, 0.95, 0.35), (0.35, -0.25, -0.8))  # (right, up, front) directions of key and fill light
_LIGHT_POWER = (0.55, 0.25)  # key + fill + ambient = 1.1: lit faces reach the texture's full range
_FIT_MARGIN = 1.15  # camera distance keeps the bounding sphere this much inside the narrower field of view
_TEXTURE_TILES = 1.5  # texture repeats per object diameter in the triplanar mapping


@functools.lru_cache(maxsize=None)
def _texture(name: str) -> np.ndarray:
    import skimage.data

    if name not in TEXTURES:
        raise ValueError(f"texture must be one of {TEXTURES} (scikit-image's bundled images), got {name!r}")
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
    """n directions (right, up, front coords) evenly spread over the band up-component in [z_lo, z_hi]."""
    k = np.arange(n) + 0.5
    z = z_hi - (z_hi - z_lo) * k / n
    r = np.sqrt(np.clip(1 - z * z, 0, None))
    phi = k * math.pi * (3 - math.sqrt(5)) + phase  # golden angle
    return np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)


def rig_cameras(rig: str, n_views: int, center, radius: float, *, resolution, up=(0, 0, 1), fov: float = 0.7,
                seed: int = 0) -> list[Camera]:
    """Cameras looking at a bounding sphere (``center``, ``radius``) from a rig.

    Args:
        rig: ``"sphere"`` (Fibonacci over the full sphere), ``"hemisphere"`` (upper half, 5 to 80
            degrees elevation), ``"orbit"`` (one ring at 25 degrees elevation) or ``"forward"``
            (parallel cameras on a grid in front of the object, LLFF-like).
        n_views: number of cameras (>= 1).
        center: sphere centre [3], world units.
        radius: sphere radius, world units.
        resolution: image size as ``int`` (square) or ``(width, height)``.
        up: world up direction.
        fov: field of view of the narrower image side, radians.
        seed: rotates the rig about ``up`` (deterministic).
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
            e = math.radians(25)
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


def from_mesh(mesh, *, n_views: int = 32, resolution=128, rig: str = "sphere", texture: str = "astronaut",
              background="black", seed: int = 0, mapping: str = "triplanar", up=(0, 0, 1), fov: float = 0.7,
              n_test: int = 0, name: str = "mesh"):
    """Render a synthetic scene of a triangle mesh.

    Args:
        mesh: ``trimesh.Trimesh`` or ``(verts [V, 3], faces [F, 3])``; kept as ``gt_mesh``, in its frame.
        n_views: training views.
        resolution: image size, ``int`` or ``(width, height)``.
        rig: camera rig (see :func:`rig_cameras`).
        texture: scikit-image picture used as the object's albedo (see :data:`TEXTURES`).
        background: ``"black"``, ``"white"`` or 3 floats (constant; masks are returned), or
            ``"room"`` (textured floor, walls and ceiling; no masks) or ``"ground"`` (a textured
            floor under the object, constant black elsewhere; no masks). Only the object is
            ``gt_mesh``.
        seed: rig rotation and texture offset (the scene is deterministic given it).
        mapping: ``"triplanar"`` or ``"spherical"`` texture projection.
        up: world up direction (floor, lights and rigs use it).
        fov: field of view of the narrower image side, radians.
        n_test: extra held-out views (another rotation of the same rig) appended after the
            training views and listed in ``test_indices``.
        name: scene name.

    Returns:
        :class:`wtopo.Scene` with images, depths (z-depth, 0 on misses), camera-facing normals,
        masks (constant backgrounds only), ``gt_mesh`` and ``background``.
    """
    import trimesh

    from .ops import raycast_mesh
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
    scenery = background if isinstance(background, str) and background in ("room", "ground") else None
    if scenery is None:
        bg = _BACKGROUNDS.get(background) if isinstance(background, str) else background
        if bg is None or np.asarray(bg, dtype=np.float64).shape != (3,):
            raise ValueError(f"background must be 'black', 'white', 3 floats, 'room' or 'ground', got {background!r}")
        bg = tuple(float(x) for x in bg)
    elif rig == "sphere":
        raise ValueError(f"background={background!r} puts a floor under the object: use rig 'hemisphere', "
                         "'orbit' or 'forward', got 'sphere'")
    if isinstance(n_test, bool) or int(n_test) != n_test or n_test < 0:
        raise ValueError(f"n_test must be an integer >= 0, got {n_test!r}")

    frame = _frame_from_up(up)
    used = verts[np.unique(faces)]
    center = 0.5 * (used.min(0) + used.max(0))
    radius = float(np.linalg.norm(used - center, axis=1).max())
    cams = rig_cameras(rig, n_views, center, radius, resolution=resolution, up=frame[1], fov=fov, seed=seed)
    if n_test:
        cams += [replace_name(c, f"test_{k:03d}") for k, c in enumerate(
            rig_cameras(rig, n_test, center, radius, resolution=resolution, up=frame[1], fov=fov, seed=seed + 7919))]

    all_v, all_f, n_obj = verts, faces, len(faces)
    if scenery is not None:
        floor = float((used @ frame[1]).min())
        dist = max(float(np.linalg.norm(c.center - center)) for c in cams)
        rv, rf = _room(center, radius, frame, floor, 1.5 * dist)
        if scenery == "ground":
            rf = rf[:2]
        all_v = np.concatenate([verts, rv])
        all_f = np.concatenate([faces, rf + len(verts)])

    rng = np.random.default_rng(seed)
    offset = rng.uniform(0, 1, size=3)
    tex = _texture(texture)
    wall_tex, floor_tex = _texture("brick"), _texture("gravel")
    lights = [np.asarray(d) @ frame for d in _LIGHTS]
    lights = [d / np.linalg.norm(d) for d in lights]

    vt = torch.as_tensor(all_v, dtype=torch.float32)
    ft = torch.as_tensor(all_f, dtype=torch.int32)
    n = len(cams)
    H, W = cams[0].height, cams[0].width
    images = np.zeros((n, H, W, 3), np.float32)
    depths = np.zeros((n, H, W), np.float32)
    normals = np.zeros((n, H, W, 3), np.float32)
    masks = np.zeros((n, H, W), bool)
    with torch.no_grad():
        for i, cam in enumerate(cams):
            r = raycast_mesh(vt, ft, cam)
            hit = r.mask.numpy()
            fid = r.face_id.numpy()[hit].astype(np.int64)
            o, d = (x.numpy().astype(np.float64) for x in cam.pixel_rays("cpu", torch.float64))
            z = r.depth.numpy().astype(np.float64)[hit]
            p = o[hit] + z[:, None] * d[hit]
            nrm = r.normal.numpy().astype(np.float64)[hit]
            facing = np.einsum("ij,ij->i", nrm, d[hit]) > 0
            nrm[facing] *= -1  # towards the camera
            obj = fid < n_obj
            alb = np.zeros((len(p), 3))
            if obj.any():
                if mapping == "triplanar":
                    alb[obj] = _triplanar(tex, p[obj] - center, nrm[obj], 2 * radius / _TEXTURE_TILES, offset)
                else:
                    alb[obj] = _spherical(tex, p[obj], center, frame, offset)
            if (~obj).any():
                is_floor = (fid >= n_obj) & (fid < n_obj + 2)
                period = radius
                for sel, t in ((is_floor, floor_tex), (~obj & ~is_floor, wall_tex)):
                    if sel.any():
                        alb[sel] = _triplanar(t, p[sel] - center, nrm[sel], period, offset)
                alb[is_floor] *= np.array([0.75, 0.7, 0.6])  # sand-coloured floor, reddish brick walls
                alb[~obj & ~is_floor] *= np.array([0.9, 0.55, 0.45])
            shade = _AMBIENT + sum(pw * np.clip(nrm @ ld, 0, None) for pw, ld in zip(_LIGHT_POWER, lights))
            img = np.empty((H, W, 3))
            img[:] = bg if scenery is None else (0.0, 0.0, 0.0)
            img[hit] = alb * shade[:, None]
            images[i] = np.clip(img, 0, 1)
            depths[i][hit] = z
            normals[i][hit] = nrm
            m = np.zeros(hit.shape, bool)
            m[hit] = obj
            masks[i] = m
    gt = trimesh.Trimesh(verts, faces, process=False)
    split = {}
    if n_test:
        split = dict(train_indices=np.arange(n_views), test_indices=np.arange(n_views, n))
    return Scene(cams, images, masks=masks if scenery is None else None, depths=depths, normals=normals,
                 gt_mesh=gt, background=bg if scenery is None else None, name=name,
                 info={"rig": rig, "texture": texture, "mapping": mapping, "seed": seed,
                       "up": frame[1].tolist()}, **split)


def replace_name(camera: Camera, name: str) -> Camera:
    """The same camera under another name."""
    return Camera(camera.K, camera.world_to_camera, camera.width, camera.height, camera.distortion, name)


@functools.lru_cache(maxsize=1)
def _bunny_arrays():
    from pxr import Usd, UsdGeom
    import warp.examples

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
            no masks) or ``"sphere"`` (12 views of 40 px of a radius-1 icosphere, for tests).
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
