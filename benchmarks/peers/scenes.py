# SPDX-License-Identifier: Apache-2.0
"""The peers benchmark's synthetic scenes beyond wtopo's built-ins, each with its full ground truth.

* The hard suite's objects (``benchmarks/objects.py``, the shapes and seeds of ``lab/hard_scenes.py``) at the
  GPU rig: 64 training views of 512 px over the sphere, black background, masks, 8 held-out views from another
  rotation of the rig: ``torus``, ``mug``, ``chair``, ``bowl``, ``blob_flat`` (flat grey albedo: shading
  only); and three of them from 10 views (``mug_sparse``, ``torus_sparse``, ``chair_sparse``).
* Two unbounded scenes with other objects, textures and rigs than ``bunny_env`` (an orbit of the bunny),
  on the same unbounded environment (a textured ground 80 object radii wide, a ring of hills, a sky at
  infinity), no masks, 1 % pixel noise, +-10 % exposure and +-3 % white balance per training image,
  48 training + 8 held-out views of 320 x 240 px; the truth is all geometry and the region of interest
  ``info["roi"]`` says what the ROI F-score is taken over:

  - ``chair_env``: the chair (thin legs, a back-rest loop) from a hemisphere of cameras looking down,
    textured with ``chelsea``;
  - ``mug_torus_env``: the mug beside an upright torus (two objects, two through-holes), textured with
    ``coffee``, from a forward-facing 7 x 7 grid (LLFF-like: their backs are never seen).

``load(name)`` returns a :class:`wtopo.Scene`; ``names()`` lists them.
"""

from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import objects  # noqa: E402

VIEWS, RESOLUTION, SPARSE_VIEWS, N_TEST = 64, 512, 10, 8
ENV_VIEWS, ENV_RESOLUTION = 48, (320, 240)

# name -> (mesh builder, texture, seed, training views): the hard suite's textures and seeds
_OBJECTS = {
    "torus": (objects.torus_mesh, "astronaut", 0, VIEWS),
    "mug": (objects.mug_mesh, "astronaut", 1, VIEWS),
    "chair": (objects.chair_mesh, "astronaut", 2, VIEWS),
    "bowl": (objects.bowl_mesh, "coffee", 3, VIEWS),
    "blob_flat": (objects.blob_mesh, "flat", 4, VIEWS),
    "mug_sparse": (objects.mug_mesh, "astronaut", 5, SPARSE_VIEWS),
    "torus_sparse": (objects.torus_mesh, "astronaut", 7, SPARSE_VIEWS),
    "chair_sparse": (objects.chair_mesh, "astronaut", 8, SPARSE_VIEWS),
}


def _mug_and_torus():
    """The mug (base on z = 0) and beside it an upright torus (major 0.3, minor 0.09) standing on the floor,
    its hole facing the forward rig's cameras (which look along +x)."""
    import trimesh

    torus = trimesh.creation.torus(major_radius=0.3, minor_radius=0.09, major_sections=96, minor_sections=48)
    torus.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))  # stands in y-z
    torus.apply_translation((0.2, 0.95, -float(torus.vertices[:, 2].min())))
    mug = objects.mug_mesh()
    mug.apply_translation((0.0, 0.0, -float(mug.vertices[:, 2].min())))
    return trimesh.util.concatenate([mug, torus])


# name -> (mesh builder, rig, texture, seed)
_UNBOUNDED = {
    "chair_env": (objects.chair_mesh, "hemisphere", "chelsea", 21),
    "mug_torus_env": (_mug_and_torus, "forward", "coffee", 22),
}


def names() -> tuple[str, ...]:
    return (*_OBJECTS, *_UNBOUNDED)


def load(name: str, **overrides):
    """The scene ``name`` (module docstring); ``overrides`` go to :func:`wtopo.scenes.from_mesh` (tests use
    small ``n_views`` / ``resolution``)."""
    from wtopo import scenes

    if name in _OBJECTS:
        build, texture, seed, views = _OBJECTS[name]
        kw = dict(n_views=views, resolution=RESOLUTION, rig="sphere", texture=texture, background="black",
                  seed=seed, up=(0, 0, 1), n_test=N_TEST, name=name)
    elif name in _UNBOUNDED:
        build, rig, texture, seed = _UNBOUNDED[name]
        kw = dict(n_views=ENV_VIEWS, resolution=ENV_RESOLUTION, rig=rig, texture=texture, background="environment",
                  seed=seed, up=(0, 0, 1), n_test=N_TEST, name=name,
                  photometric=scenes.Photometric(noise=0.01, exposure=0.1, white_balance=0.03))
    else:
        raise ValueError(f"name must be one of {names()}, got {name!r}")
    return scenes.from_mesh(build(), **{**kw, **overrides})
