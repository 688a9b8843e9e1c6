# SPDX-License-Identifier: Apache-2.0
"""Silhouette calibration of the proxy mesh (wtopo.fitting.silhouette): normals, mask boundary, the
per-view measure on analytic masks, and the closed loop that moves a shrunk proxy onto the masks."""

import math

import numpy as np
import pytest
import torch
import trimesh
from shapes import sphere_lattice

from wtopo.camera import Camera
from wtopo.fitting.config import MeshConfig
from wtopo.fitting.proxy import ProxyMesh
from wtopo.fitting.silhouette import SilhouetteOffset, mask_boundary, vertex_normals
from wtopo.fitting.surfels import Surfels
from wtopo.raycast import MeshRaycaster


def _square(h, w, lo, hi):
    m = torch.zeros(h, w, dtype=torch.bool)
    m[lo:hi, lo:hi] = True
    return m


def test_vertex_normals_point_outwards_on_marching_cubes_output():
    from wtopo.marching_cubes import marching_cubes

    r = 24
    g = torch.linspace(0, 1, r, dtype=torch.float64)
    x, y, z = torch.meshgrid(g, g, g, indexing="ij")
    field = torch.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2) - 0.3  # negative inside
    verts, faces = marching_cubes(field, 0.0, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0))
    assert faces.shape[0] > 100
    n = vertex_normals(verts, faces)
    radial = verts.detach() - 0.5
    radial = radial / radial.norm(dim=-1, keepdim=True)
    cos = (n * radial).sum(-1)
    assert float(cos.min()) > 0.9, "vertex normals of a marching-cubes sphere point outwards"
    assert torch.allclose(n.norm(dim=-1), torch.ones(n.shape[0], dtype=n.dtype), atol=1e-6)


def test_mask_boundary_of_a_square_is_its_outline():
    m = _square(20, 20, 5, 15)  # 10 x 10
    b = mask_boundary(m)
    assert int(b.sum()) == 4 * 10 - 4
    assert not bool(b[6:14, 6:14].any()) and bool(b[5, 5:15].all())
    full = torch.ones(8, 8, dtype=torch.bool)  # image borders count as inside: no boundary
    assert int(mask_boundary(full).sum()) == 0


def test_measure_is_the_shrink_times_the_footprint():
    h = w = 64
    mask = _square(h, w, 12, 52)  # side 40
    depth = torch.full((h, w), 2.0)
    fx = 100.0
    cal = SilhouetteOffset(gain=1.0, limit=1.0)
    inside = _square(h, w, 13, 51)  # one pixel inside on every side: missed = boundary pixels exactly
    got = float(cal.measure(inside, depth * inside, mask, fx))
    assert got == pytest.approx(1.0 * 2.0 / fx, rel=1e-6)
    outside = _square(h, w, 11, 53)  # one pixel outside: negative, (4 S + 4) / (4 S - 4) pixels
    got = float(cal.measure(outside, depth * outside, mask, fx))
    assert got == pytest.approx(-(4 * 40 + 4) / (4 * 40 - 4) * 2.0 / fx, rel=1e-6)
    assert float(cal.measure(mask, depth * mask, mask, fx)) == 0.0  # on the mask: nothing to move
    none = torch.zeros(h, w, dtype=torch.bool)  # the proxy misses the view: no rim depth, no measure
    assert float(cal.measure(none, depth * 0, mask, fx)) == 0.0
    cal.update(inside, depth * inside, mask, fx)
    assert float(cal.value) == pytest.approx(0.02, rel=1e-6)
    for _ in range(200):  # clamped to the limit
        cal.update(inside, depth * inside, mask, fx)
    assert float(cal.value) == pytest.approx(1.0)


@pytest.mark.parametrize("bad", [dict(gain=0.0, limit=1.0), dict(gain=1.5, limit=1.0), dict(gain=0.5, limit=0.0)])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match="gain|limit"):
        SilhouetteOffset(**bad)


def _sphere_surfels(radius: float, n: int) -> Surfels:
    nrm, p, sigma = sphere_lattice(n, radius)
    return Surfels.from_points(torch.as_tensor(0.5 + p, dtype=torch.float32), torch.full((n, 3), 0.5),
                               scales=torch.full((n,), sigma), normals=torch.as_tensor(nrm, dtype=torch.float32),
                               opacity=0.95)


def _ring(n: int) -> list[Camera]:
    """``n`` cameras on a ring 1.6 from the unit cube's centre, looking at it (96 px, fov 0.6)."""
    return [Camera.look_at(0.5 + 1.6 * np.array([math.cos(a), math.sin(a), 0.3]), [0.5, 0.5, 0.5], [0, 0, 1],
                           fov_x=0.6, width=96, height=96) for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def _sphere_masks(radius: float, cams) -> list[torch.Tensor]:
    """Ray-cast masks of a sphere of ``radius`` at the unit cube's centre."""
    s = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    v, f = torch.as_tensor(s.vertices + 0.5, dtype=torch.float32), torch.as_tensor(s.faces, dtype=torch.int32)
    rc = MeshRaycaster()
    return [rc.raycast(v, f, c).mask.clone() for c in cams]


def test_closed_loop_moves_a_shrunk_proxy_onto_the_masks():
    """Surfels on a sphere of radius 0.25, masks of a sphere of radius 0.27: the running offset grows
    the proxy until its silhouettes match, i.e. to the masks' radius (within a fraction of a pixel)."""
    true_r, surf_r = 0.27, 0.25
    cams = _ring(6)
    masks = _sphere_masks(true_r, cams)
    assert all(int(m.sum()) > 500 for m in masks)
    s = _sphere_surfels(surf_r, 1500)
    proxy = ProxyMesh(MeshConfig(resolution=48, silhouette_gain=0.5))
    assert proxy.silhouette is not None and ProxyMesh(MeshConfig(resolution=48, silhouette_gain=0.0)).silhouette is None

    def radius(pm):
        return float((pm.verts.detach() - 0.5).norm(dim=-1).mean())

    with torch.no_grad():
        r0 = radius(proxy.build(s))
        for it in range(36):
            pm = proxy.build(s)
            cam = cams[it % len(cams)]
            mr = proxy.render(pm, cam)
            proxy.silhouette.update(mr.mask, mr.depth, masks[it % len(cams)], float(cam.K[0, 0]))
        r1 = radius(proxy.build(s))
    pixel = 1.6 / cams[0].K[0, 0]  # footprint at the sphere's distance
    assert abs(r0 - true_r) > 1.5 * pixel, "the test needs a proxy well inside the masks to start with"
    assert abs(r1 - true_r) < 0.5 * pixel, (r0, r1, true_r, pixel)
    # the offset mesh stays differentiable w.r.t. the surfels
    pm = proxy.build(s)
    pm.verts.sum().backward()
    assert s.means.grad is not None and float(s.means.grad.abs().sum()) > 0


def test_calibrate_mesh_moves_a_shrunk_sphere_onto_the_masks_within_its_limit():
    """A sphere mesh half a pixel inside the masks comes out on them; a gap of 2 px is cut at 1 px."""
    from wtopo.fitting.silhouette import calibrate_mesh

    cams = _ring(8)
    pixel = 1.6 / cams[0].K[0, 0]
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.25)
    v = torch.as_tensor(sphere.vertices + 0.5, dtype=torch.float32)
    f = torch.as_tensor(sphere.faces, dtype=torch.int32)
    for gap_px, expect_px in ((0.5, 0.5), (2.0, 1.0)):
        masks = _sphere_masks(0.25 + gap_px * pixel, cams)
        out, info = calibrate_mesh(v, f, cams, masks)
        r = float((out - 0.5).norm(dim=-1).mean())
        assert out.shape == v.shape and out.dtype == v.dtype and len(info["rounds"]) == 3
        assert abs(r - (0.25 + expect_px * pixel)) < 0.25 * pixel, (gap_px, r, info)
        assert info["offset_px"] == pytest.approx(expect_px, abs=0.25)
