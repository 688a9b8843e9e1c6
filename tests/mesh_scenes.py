# SPDX-License-Identifier: Apache-2.0
"""Scenes of the mesh-policy tests (``test_mesh_policy.py``, ``test_final_mesh_repair.py``): a ring of cameras, the
depth maps they see of a mesh, and a seen pair of objects with a lone sphere and a speck beside it."""

import numpy as np
import trimesh

from wtopo import Camera


def ring_cameras(n=8, radius=4.0, size=64):
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 1.0])
        cams.append(Camera.look_at(eye, np.zeros(3), np.array([0, 0, 1.0]), fov_x=0.9, width=size, height=size))
    return cams


def depths_of(mesh, cams):
    import torch

    from wtopo.ops import raycast_mesh

    v = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    f = torch.as_tensor(mesh.faces, dtype=torch.int32)
    out = []
    for c in cams:
        r = raycast_mesh(v, f, c)
        out.append(torch.where(r.mask, r.depth, torch.zeros_like(r.depth)).numpy())
    return out


def seen_pair():
    """A torus and a capsule side by side: what the ring of cameras sees."""
    torus = trimesh.creation.torus(0.6, 0.2)
    torus.apply_translation([-0.7, 0, 0])
    capsule = trimesh.creation.capsule(height=0.6, radius=0.2)
    capsule.apply_translation([0.8, 0, 0])
    return trimesh.util.concatenate([torus, capsule])


def pair_lone_and_speck(cams):
    """``(mesh, seen, depths)``: the seen pair, a sphere only cams[0] and cams[1] see (below _MIN_SUPPORT_VIEWS)
    and a speck in no depth map; the depths are the pair's, with the sphere added in those two views."""
    seen = seen_pair()
    depths = depths_of(seen, cams)
    lone = trimesh.creation.icosphere(subdivisions=2, radius=0.15)
    lone.apply_translation([0, 0, 1.0])
    for k in (0, 1):
        depths[k] = np.where(depths[k] > 0, depths[k], depths_of(lone, [cams[k]])[0])
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    speck.apply_translation([0, 0.9, 0.9])
    return trimesh.util.concatenate([seen, lone, speck]), seen, depths

