# SPDX-License-Identifier: Apache-2.0
"""The support rules' projection (``kernels/vertex_support.py`` through :func:`wtopo.vertex_support.view_agreement`):
the NumPy reference on a ray-cast sphere (pinhole, skew and a distorted lens, relative and absolute tolerances),
and the stiff cases (a vertex at the camera centre, behind it, on the image border, NaN, an empty list). The mesh
policy's rules on every device: ``tests/test_mesh_policy.py``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh
from reference.vertex_support import view_agreement_numpy

from wtopo import Camera
from wtopo.ops import raycast_mesh
from wtopo.vertex_support import view_agreement


def _view(distortion=None, skew=0.0):
    cam = Camera.look_at(np.array([2.5, 0.5, 1.0]), np.zeros(3), np.array([0, 0, 1.0]), fov_x=0.9, width=96,
                         height=80)
    K = cam.K.copy()
    K[0, 1] = skew
    return dataclasses.replace(cam, K=K, distortion=None if distortion is None else np.asarray(distortion))


@pytest.mark.parametrize("lens", ["pinhole", "skew", "barrel"])
def test_matches_the_numpy_projection_on_a_sphere(device, lens):
    sphere = trimesh.creation.icosphere(subdivisions=4)
    cam = _view((-0.2, 0.03, 0.001, -0.002, 0.0) if lens == "barrel" else None, 4.0 if lens == "skew" else 0.0)
    r = raycast_mesh(torch.as_tensor(sphere.vertices, dtype=torch.float32),
                     torch.as_tensor(sphere.faces, dtype=torch.int32), [cam])
    depth = np.where(r.mask[0].numpy(), r.depth[0].numpy(), 0.0)
    verts = np.asarray(sphere.vertices)
    idx = torch.arange(len(verts), device=device)
    for tol in (None, 0.01):
        want = view_agreement_numpy(verts, cam, depth, tol)
        got = view_agreement(torch.as_tensor(verts, device=device), idx, cam, torch.as_tensor(depth, device=device),
                             tolerance=tol)
        assert 0.1 < want.mean() < 0.6, "not exercised: part of the half facing the camera agrees"
        np.testing.assert_array_equal(got.cpu().numpy(), want)


def test_one_vertex_a_thread_gives_the_same(monkeypatch):
    """CUDA's layout (one vertex a thread) run on the CPU: the same answers as the CPU's strips."""
    import wtopo.vertex_support as vs

    sphere = trimesh.creation.icosphere(subdivisions=3)
    cam = _view()
    r = raycast_mesh(torch.as_tensor(sphere.vertices, dtype=torch.float32),
                     torch.as_tensor(sphere.faces, dtype=torch.int32), [cam])
    depth = torch.where(r.mask[0], r.depth[0], torch.zeros_like(r.depth[0]))
    verts = torch.as_tensor(sphere.vertices)
    idx = torch.arange(len(verts)).flip(0)
    strips = view_agreement(verts, idx, cam, depth)
    monkeypatch.setattr(vs, "_CPU_STRIP", 1)
    assert strips.any() and torch.equal(view_agreement(verts, idx, cam, depth), strips)


def test_stiff_vertices_do_not_agree(device):
    cam = _view()
    depth = torch.full((cam.height, cam.width), 1.0, dtype=torch.float64, device=device)
    fwd = cam.forward
    c = cam.center
    # at the centre (z = 0), behind, NaN, far off the image; then one that agrees: 1.0 ahead on the optical axis
    verts = torch.as_tensor(np.stack([c, c - fwd, np.full(3, np.nan), c + fwd + 50.0 * cam.R[0], c + fwd]),
                            device=device)
    got = view_agreement(verts, torch.arange(5, device=device), cam, depth, tolerance=1e-6)
    assert got.cpu().tolist() == [False, False, False, False, True]
    empty = view_agreement(verts, torch.zeros(0, dtype=torch.int64, device=device), cam, depth)
    assert empty.shape == (0,) and empty.dtype == torch.bool


def test_bad_arguments_are_named():
    cam = _view()
    v = torch.zeros(4, 3, dtype=torch.float64)
    i = torch.arange(4)
    d = torch.ones(cam.height, cam.width)
    with pytest.raises(TypeError, match="vertices"):
        view_agreement(v.float(), i, cam, d)
    with pytest.raises(TypeError, match="index"):
        view_agreement(v, i.int(), cam, d)
    with pytest.raises(ValueError, match="depth"):
        view_agreement(v, i, cam, d[:, :10])
    with pytest.raises(ValueError, match="index"):
        view_agreement(v, torch.tensor([0, 4]), cam, d)
    with pytest.raises(ValueError, match="tolerance"):
        view_agreement(v, i, cam, d, tolerance=0.0)
    with pytest.raises(ValueError, match="relative"):
        view_agreement(v, i, cam, d, relative=float("nan"))
