# SPDX-License-Identifier: Apache-2.0
"""Mean curvature of a mesh and the proxy's curvature compensation (``wtopo.fitting.curvature``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from wtopo.fitting.config import MeshConfig
from wtopo.fitting.curvature import curvature_offset, mean_curvature
from wtopo.fitting.proxy import ProxyMesh, poisson_mesh
from wtopo.fitting.surfels import Surfels

_R, _r = 0.28, 0.09  # torus in the unit cube: ring radius, tube radius


def _torus_mean_curvature(p: np.ndarray) -> np.ndarray:
    """Exact mean curvature (k1 + k2) / 2 of the torus about z at points ``p`` near it."""
    rho = np.hypot(p[:, 0], p[:, 1])
    cos_v = np.clip((rho - _R) / _r, -1.0, 1.0)
    return (_R + 2.0 * _r * cos_v) / (2.0 * _r * (_R + _r * cos_v))


def _torus_sd(p: np.ndarray) -> np.ndarray:
    return np.hypot(np.hypot(p[:, 0], p[:, 1]) - _R, p[:, 2]) - _r


def test_sphere_has_curvature_one_over_radius_and_no_offset():
    s = trimesh.creation.icosphere(subdivisions=4, radius=0.7)
    v, f = torch.as_tensor(s.vertices), torch.as_tensor(s.faces, dtype=torch.int32)
    h, h_mean = mean_curvature(v, f)
    assert h.shape == (v.shape[0],) and h.dtype == torch.float64
    np.testing.assert_allclose(h.numpy(), 1 / 0.7, rtol=0.08)  # the icosahedron's 12 valence-5 vertices: -6 %
    assert abs(float(h_mean) - 1 / 0.7) < 0.02 / 0.7
    off = curvature_offset(v, f, 0.01, 1.0)
    assert float(off.norm(dim=-1).max()) < 0.01 * 0.1 / 0.7  # H == H_mean up to the mesh: (almost) no displacement


def test_flat_patch_has_zero_curvature_and_inverted_winding_flips_the_sign():
    g = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    for _ in range(4):
        g = g.subdivide()
    v, f = torch.as_tensor(g.vertices), torch.as_tensor(g.faces, dtype=torch.int32)
    h, _ = mean_curvature(v, f)
    centre = (np.abs(g.vertices) < 0.4).sum(1) >= 2  # face interiors, two rings and more from every edge
    assert centre.sum() > 10 and np.abs(h.numpy()[centre]).max() < 1e-9
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    inv = torch.as_tensor(s.faces[:, ::-1].copy(), dtype=torch.int32)
    hi, _ = mean_curvature(torch.as_tensor(s.vertices), inv)
    assert float(hi.max()) < 0  # seen from the inside the sphere is concave


def test_torus_curvature_matches_the_analytic_one():
    m = trimesh.creation.torus(major_radius=_R, minor_radius=_r, major_sections=256, minor_sections=96)
    h, h_mean = mean_curvature(torch.as_tensor(m.vertices), torch.as_tensor(m.faces, dtype=torch.int32))
    exact = _torus_mean_curvature(m.vertices)
    assert exact.max() > 1.5 * exact.min()  # the outer ring is more curved than the inner one
    assert np.sqrt(np.mean((h.numpy() - exact) ** 2)) < 0.03 * np.abs(exact).max()
    # over a torus's area k1 = 1 / r integrates to A / r and k2 = cos v / (R + r cos v) to 0, so H_mean = 1 / (2 r)
    assert abs(float(h_mean) - 1 / (2 * _r)) < 0.02 / _r


@pytest.mark.parametrize("sigma", [1.0, 0.5, 0.0])
def test_poisson_shift_follows_the_curvature(sigma):
    """Oriented points on the exact torus -> Poisson at 64^3: the vertices' signed distance fits
    -(sigma^2 + 1/6) h^2 (H - H_mean) (the exact H at each vertex)."""
    m = trimesh.creation.torus(major_radius=_R, minor_radius=_r, major_sections=400, minor_sections=200)
    p, fid = trimesh.sample.sample_surface_even(m, 150_000, seed=0)
    rho = np.hypot(p[:, 0], p[:, 1])
    ring = np.stack([p[:, 0] / rho * _R, p[:, 1] / rho * _R, np.zeros_like(rho)], -1)
    n = (p - ring) / np.linalg.norm(p - ring, axis=1, keepdims=True)
    p = ring + _r * n  # exactly on the torus, with exact normals
    res, pad = 64, 0.1
    v, f = poisson_mesh(torch.as_tensor(p + 0.5), torch.as_tensor(n), torch.ones(len(p), dtype=torch.float64),
                        res, sigma=sigma, padding=pad)
    assert f.shape[0] > 1000
    h = (1 + 2 * pad) / (res - 1)
    vv = v.numpy() - 0.5
    dh = _torus_mean_curvature(vv) - _torus_mean_curvature(p).mean()
    slope = np.linalg.lstsq(np.vstack([dh, np.ones_like(dh)]).T, _torus_sd(vv), rcond=None)[0][0]
    assert slope == pytest.approx(-(sigma ** 2 + 1 / 6) * h * h, rel=0.15)


def test_compensation_brings_a_box_proxy_closer_to_the_box():
    """A bar 0.12 x 0.2 x 0.6 (6-10 cells thick at 64^3) from its exact oriented points: Poisson puts
    its flat faces outside and its edges inside; the compensated vertices lie closer to it."""
    ext = np.array([0.6, 0.12, 0.2])
    m = trimesh.creation.box(extents=ext)
    p, fid = trimesh.sample.sample_surface_even(m, 100_000, seed=0)
    v, f = poisson_mesh(torch.as_tensor(p + 0.5), torch.as_tensor(m.face_normals[fid]),
                        torch.ones(len(p), dtype=torch.float64), 64, sigma=1.0, padding=0.1)
    h = 1.2 / 63

    def rms(q):
        d = np.abs(q) - ext / 2
        sd = np.linalg.norm(np.maximum(d, 0), axis=1) + np.minimum(d.max(1), 0)
        return np.sqrt(np.mean(sd ** 2))

    vv = v.numpy() - 0.5
    before, after = rms(vv), rms(vv + curvature_offset(v, f, (1 + 1 / 6) * h * h, 0.5 * h).numpy())
    assert before > 0.15 * h  # the shift is there to undo (0.21 cells rms)
    assert after < 0.75 * before  # measured 0.13 cells


def test_degenerate_faces_give_finite_curvature_in_float32():
    """Marching cubes can emit faces with a repeated vertex or zero area: the per-face 3 x 3 solve must
    not fail (it did in float32 on the CPU) and must not return NaN."""
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    v = torch.as_tensor(s.vertices, dtype=torch.float32)
    f = torch.as_tensor(s.faces, dtype=torch.int32)
    bad = torch.tensor([[0, 0, 1], [2, 2, 2], [3, 4, 3]], dtype=torch.int32)  # collapsed faces
    v2 = torch.cat([v, v[:1]])  # and a duplicated vertex used by a zero-area face
    f2 = torch.cat([f, bad, torch.tensor([[0, v.shape[0], 5]], dtype=torch.int32)])
    h, h_mean = mean_curvature(v2, f2)
    assert h.dtype == torch.float32 and bool(torch.isfinite(h).all()) and bool(torch.isfinite(h_mean))
    np.testing.assert_allclose(h[: v.shape[0]].numpy(), 2.0, rtol=0.15)
    assert bool(torch.isfinite(curvature_offset(v2, f2, 1e-4, 1e-2)).all())


def test_offset_is_clamped_and_arguments_are_checked():
    m = trimesh.creation.torus(major_radius=_R, minor_radius=_r, major_sections=64, minor_sections=32)
    v, f = torch.as_tensor(m.vertices), torch.as_tensor(m.faces, dtype=torch.int32)
    off = curvature_offset(v, f, 1.0, 1e-3)
    assert float(off.norm(dim=-1).max()) == pytest.approx(1e-3, rel=1e-6)
    with pytest.raises(ValueError, match="variance"):
        curvature_offset(v, f, -1.0, 1.0)
    with pytest.raises(ValueError, match="limit"):
        curvature_offset(v, f, 1.0, -1.0)
    h, h_mean = mean_curvature(v, torch.zeros((0, 3), dtype=torch.int32))
    assert float(h.abs().sum()) == 0 and float(h_mean) == 0


def test_compensated_proxy_keeps_its_gradient():
    """The offset is discrete: the proxy's vertices stay differentiable w.r.t. the surfels, with the
    same gradient as without it."""
    m = trimesh.creation.torus(major_radius=_R, minor_radius=_r, major_sections=48, minor_sections=24)
    p, fid = trimesh.sample.sample_surface_even(m, 3000, seed=1)
    nrm = m.face_normals[fid]

    def build(comp: bool):
        s = Surfels.from_points(torch.as_tensor(p + 0.5, dtype=torch.float32), torch.full((len(p), 3), 0.5),
                                scales=torch.full((len(p),), 0.01), normals=torch.as_tensor(nrm, dtype=torch.float32),
                                opacity=0.9)
        px = ProxyMesh(MeshConfig(resolution=48, curvature_compensation=comp))
        r = px.build(s)
        assert r is not None and r.num_faces > 100
        (r.verts * torch.tensor([0.3, -0.5, 0.8])).sum().backward()
        return r.verts.detach(), s.means.grad

    v0, g0 = build(False)
    v1, g1 = build(True)
    assert v0.shape == v1.shape and float((v1 - v0).norm(dim=-1).max()) > 0  # it moved something
    assert float((v1 - v0).norm(dim=-1).max()) <= 0.5 * 1.2 / 47 + 1e-6  # at most half a cell
    assert g0 is not None and float(g0.abs().sum()) > 0 and g1 is not None
    torch.testing.assert_close(g1, g0)  # the vertices moved, their path to the surfels did not
