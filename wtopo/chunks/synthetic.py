# SPDX-License-Identifier: Apache-2.0
"""A large synthetic scene with ground truth for chunked fitting: objects in a row on a ground.

Several primitives (sphere, box, cylinder, capsule, cone, ...) stand in a row along the world x
axis on the textured ground of the unbounded environment of :func:`wtopo.scenes.from_mesh` (up is
+z). Two camera segments film them:

* orbit segments: a ring of cameras around each object, looking at it;
* a forward segment: a drive-by line of cameras in front of the row (at ``y < 0``), all looking
  the same way (+y, forward-facing: parallel optical axes).

Each camera sees only part of the row, so a chunk of the row has cameras of its own: the case
chunked fitting is for. ``Scene.bounds`` is the region of interest ``info["roi"]`` (the objects'
box, horizontal sides grown as in :data:`wtopo.scenes.ROI_HORIZONTAL_GROWTH`, ground included).
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera

__all__ = ["street_scene", "street_cameras", "street_mesh"]

_SPACING = 4.5  # object centres along x, in object radii (1): an orbit ring clears its neighbours by 0.5
_ORBIT_DISTANCE = 2.8  # orbit ring radius around each object, in object radii (inside half the spacing)
_ORBIT_HEIGHT = 1.6  # orbit camera height above the ground (objects are 2 tall: a slightly downward look)
_FORWARD_DISTANCE = 6.0  # the drive-by line's distance in front of the row
_FORWARD_HEIGHT = 1.2  # drive-by camera height
_FOV = 1.0  # radians, the narrower image side (the environment's default)
_POINT_JITTER = 0.002  # sparse points' noise, fraction of the region's diagonal (SfM points are noisy)


def _primitive(k: int):
    """The ``k``-th object of the row, radius about 1, standing on z = 0, centred on x = y = 0."""
    import trimesh

    c = trimesh.creation
    makers = (
        lambda: c.icosphere(subdivisions=3, radius=1.0),
        lambda: c.box(extents=(1.6, 1.6, 1.6)),
        lambda: c.cylinder(radius=0.8, height=2.0, sections=48),
        lambda: c.capsule(height=1.2, radius=0.7, count=(24, 24)),
        lambda: c.cone(radius=1.0, height=2.0, sections=48),
        lambda: c.annulus(r_min=0.4, r_max=0.9, height=1.6, sections=48),
    )
    m = makers[k % len(makers)]()
    m.apply_translation([0.0, 0.0, -m.bounds[0, 2]])
    return m


def street_mesh(n_objects: int):
    """The row of ``n_objects`` primitives (``trimesh.Trimesh``), object ``k`` at x = 4.5 k."""
    import trimesh

    if isinstance(n_objects, bool) or int(n_objects) != n_objects or n_objects < 1:
        raise ValueError(f"n_objects must be a positive integer, got {n_objects!r}")
    parts = []
    for k in range(int(n_objects)):
        m = _primitive(k)
        m.apply_translation([_SPACING * k, 0.0, 0.0])
        parts.append(m)
    return trimesh.util.concatenate(parts)


def street_cameras(n_objects: int, orbit_views: int, forward_views: int, resolution) -> list[Camera]:
    """Orbit rings around each object (``orbit_views`` each) then the forward drive-by line."""
    w, h = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
    fov_x = 2 * math.atan(math.tan(0.5 * _FOV) * w / min(w, h))
    up = np.array([0.0, 0.0, 1.0])
    cams = []
    for k in range(n_objects):
        target = np.array([_SPACING * k, 0.0, 0.8])
        for j in range(orbit_views):
            a = 2 * math.pi * (j + 0.5 * (k % 2)) / orbit_views
            eye = target + np.array([_ORBIT_DISTANCE * math.cos(a), _ORBIT_DISTANCE * math.sin(a), 0.0])
            eye[2] = _ORBIT_HEIGHT
            cams.append(Camera.look_at(eye, target, up, fov_x=fov_x, width=w, height=h, name=f"orbit{k}_{j:03d}"))
    x_end = _SPACING * (n_objects - 1)
    for j in range(forward_views):
        x = -1.0 + (x_end + 2.0) * j / max(forward_views - 1, 1)
        eye = np.array([x, -_FORWARD_DISTANCE, _FORWARD_HEIGHT])
        cams.append(Camera.look_at(eye, eye + np.array([0.0, 1.0, -0.1]), up, fov_x=fov_x, width=w, height=h,
                                   name=f"forward_{j:03d}"))
    return cams


def street_scene(n_objects: int = 6, *, orbit_views: int = 24, forward_views: int = 60, resolution=(200, 150),
                 seed: int = 0, photometric=None, points: int = 0):
    """Render the row scene (see the module docstring).

    Args:
        n_objects: objects in the row (>= 1).
        orbit_views: cameras in the ring around each object.
        forward_views: cameras on the drive-by line.
        resolution: image size, ``int`` or ``(width, height)``.
        seed: texture offsets, hills and clouds.
        photometric: :class:`wtopo.scenes.Photometric` imperfections, or ``None``.
        points: sparse points to give the scene (``Scene.points``, as structure from motion would):
            this many samples of the ground truth inside the region of interest, jittered by
            ``_POINT_JITTER`` of its diagonal; 0 for none (the fit then runs plane-sweep stereo).

    Returns:
        :class:`wtopo.Scene` with ``n_objects * orbit_views + forward_views`` views, depths, normals,
        ``gt_mesh`` (objects, ground and hills), ``bounds`` = ``info["roi"]``, no masks.
    """
    from .. import scenes

    for name, v in (("orbit_views", orbit_views), ("forward_views", forward_views)):
        if isinstance(v, bool) or int(v) != v or v < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {v!r}")
    mesh = street_mesh(n_objects)
    cams = street_cameras(int(n_objects), int(orbit_views), int(forward_views), resolution)
    if not cams:
        raise ValueError("orbit_views and forward_views are both 0: the scene needs cameras")
    scene = scenes.from_mesh(mesh, resolution=resolution, rig="orbit", texture="coffee", background="environment",
                            seed=seed, up=(0.0, 0.0, 1.0), name=f"street{n_objects}", photometric=photometric,
                            bounds_from_roi=True, cameras=cams)
    if points:
        scene.points = _truth_points(scene, int(points), seed)
    return scene


def _truth_points(scene, n: int, seed: int) -> np.ndarray:
    """``n`` jittered samples [n, 3] of ``scene.gt_mesh`` inside ``scene.bounds``."""
    import trimesh

    lo, hi = scene.bounds
    g = scene.gt_mesh
    c = g.triangles_center
    sub = trimesh.Trimesh(g.vertices, g.faces[np.all((c >= lo) & (c <= hi), axis=1)], process=False)
    p = trimesh.sample.sample_surface(sub, n, seed=seed)[0]
    rng = np.random.default_rng(seed)
    return p + rng.normal(0.0, _POINT_JITTER * float(np.linalg.norm(hi - lo)), p.shape)
