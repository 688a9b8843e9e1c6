# SPDX-License-Identifier: Apache-2.0
"""The hard suite's scenes (``lab/hard.py``): truth meshes built from signed distance functions
and trimesh primitives with fixed seeds, and the scenes rendered from them."""

from __future__ import annotations

import os
import sys

import numpy as np
import trimesh

from wtopo import scenes

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
from objects import (  # noqa: E402,F401  (the suite's meshes live beside the benchmarks that share them)
    MESH_CACHE,
    _bowl_sdf,
    _box,
    _chair_sdf,
    _cylinder_z,
    _mug_sdf,
    _sphere,
    _torus_y,
    blob_mesh,
    bowl_mesh,
    chair_mesh,
    clip_to_box,
    mug_mesh,
    sdf_mesh,
    torus_mesh,
)

N_TEST = 6  # held-out views per scene
RIG = {"views": 32, "resolution": 128}  # training views and pixels per side (``--gpu``: 64 of 512)


def _ground_truth_on_floor(sdf, scene, spacing: float) -> trimesh.Trimesh:
    """The object's ``sdf`` united with the half-space under its floor, meshed inside the scene's
    region of interest and clipped to it: what a reconstruction of that box should hold (the
    floor without the object's footprint, the object without the faces it stands on)."""
    lo, hi = (np.asarray(b, np.float64) for b in scene.info["roi"])
    floor = float(np.asarray(scene.gt_mesh.vertices)[:, 2].min()) + 1e-3  # feet sink 1e-3 into it
    m = sdf_mesh(lambda p: np.minimum(sdf(p), p[..., 2] - floor), lo - 2 * spacing, hi + 2 * spacing, spacing)
    return clip_to_box(m, lo, hi)


# -- the suite -------------------------------------------------------------------------------------
def _object_scene(mesh, name, texture="astronaut", n_views=None, seed=0):
    return scenes.from_mesh(mesh, n_views=n_views or RIG["views"], resolution=RIG["resolution"], rig="sphere",
                            texture=texture, background="black", seed=seed, up=(0, 0, 1), n_test=N_TEST, name=name)


def _with_box(scene, margin: float = 0.1):
    """The scene with ``Scene.bounds``: its truth's bounding box grown by ``margin`` of its diagonal
    (as datasets that ship a box give it)."""
    import dataclasses

    lo, hi = scene.gt_mesh.bounds
    pad = margin * float(np.linalg.norm(hi - lo))
    return dataclasses.replace(scene, bounds=(lo - pad, hi + pad))


def _chair_ground():
    sc = scenes.from_mesh(chair_mesh(), n_views=RIG["views"], resolution=RIG["resolution"], rig="hemisphere",
                          texture="astronaut", background="ground", seed=6, up=(0, 0, 1), n_test=N_TEST,
                          name="chair_ground", bounds_from_roi=True)
    return sc, _ground_truth_on_floor(_chair_sdf, sc, 0.008)


SCENES = {  # name -> () -> (scene, the truth to score against when not scene.gt_mesh)
    "torus": lambda: (_object_scene(torus_mesh(), "torus", seed=0), None),
    "mug": lambda: (_object_scene(mug_mesh(), "mug", seed=1), None),
    "chair": lambda: (_object_scene(chair_mesh(), "chair", seed=2), None),
    "chair_box": lambda: (_with_box(_object_scene(chair_mesh(), "chair_box", seed=2)), None),
    "bowl": lambda: (_object_scene(bowl_mesh(), "bowl", texture="coffee", seed=3), None),
    "blob_flat": lambda: (_object_scene(blob_mesh(), "blob_flat", texture="flat", seed=4), None),
    "mug_sparse": lambda: (_object_scene(mug_mesh(), "mug_sparse", n_views=10, seed=5), None),
    "torus_sparse": lambda: (_object_scene(torus_mesh(), "torus_sparse", n_views=10, seed=7), None),
    "chair_sparse": lambda: (_object_scene(chair_mesh(), "chair_sparse", n_views=10, seed=8), None),
    "chair_ground": _chair_ground,
}
DESCRIPTIONS = {
    "torus": "genus 1, textured, 32 views",
    "mug": "cup with a handle: concavity + genus 1, 32 views",
    "chair": "thin legs and seat (4 px), back-rest loop (genus 1), 32 views",
    "chair_box": "the chair with Scene.bounds given (its box + 10 % of the diagonal)",
    "bowl": "hemispherical shell: concave, self-occluding, 32 views",
    "blob_flat": "bumpy blob, flat grey albedo (shading only), 32 views",
    "mug_sparse": "the mug from 10 views",
    "torus_sparse": "the torus from 10 views",
    "chair_sparse": "the chair from 10 views",
    "chair_ground": "the chair on a textured floor, no masks, hemisphere rig, ROI given; truth: chair + floor in it",
}
