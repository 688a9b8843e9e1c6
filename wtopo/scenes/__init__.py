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

Modules (private; import from ``wtopo.scenes``): ``_rigs`` (camera rigs), ``_scenery`` (textures,
lights, room, unbounded environment, sky, shading), ``_synthetic`` (:func:`from_mesh`,
:class:`Photometric`); this module keeps the registry of named scenes (:func:`load`, :func:`names`,
:func:`bunny_mesh`).
"""

from __future__ import annotations

import functools
import os

import numpy as np

from ._rigs import RIGS, rig_cameras
from ._scenery import TEXTURES
from ._synthetic import ROI_HORIZONTAL_GROWTH, Photometric, from_mesh
from ._synthetic import replace_name as replace_name

__all__ = ["from_mesh", "load", "names", "bunny_mesh", "rig_cameras", "Photometric", "RIGS", "TEXTURES",
           "ROI_HORIZONTAL_GROWTH"]


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
