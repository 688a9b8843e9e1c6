# SPDX-License-Identifier: Apache-2.0
"""poisson_indicator's local level (``level_sigma``): gradients, a closed surface unchanged, an open sheet
beside a closed part kept on its points, and the stiff cases (its reference test is test_poisson's)."""

import numpy as np
import pytest
import torch
from skimage.measure import marching_cubes

from wtopo.ops import poisson_indicator

FLOOR_Z = 0.35  # the open sheet's height in the unit cube
BALL = (np.array([0.5, 0.5, 0.62]), 0.2)  # a closed sphere standing above the sheet


def _ball_on_floor(dtype=torch.float64, device="cpu", ball_weight=4.0):
    """Oriented points of a sphere (weight ``ball_weight``, outward) over an open sheet z = FLOOR_Z across
    the unit square (weight 1, normal +z) that ends at the cube's sides, as a ground cut by a region of interest."""
    g = torch.Generator().manual_seed(0)
    d = torch.randn(8000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    sp = torch.as_tensor(BALL[0]) + BALL[1] * d
    fl = torch.rand(20000, 2, generator=g, dtype=torch.float64)
    fl = torch.cat([fl, torch.full((20000, 1), FLOOR_Z, dtype=torch.float64)], dim=1)
    p = torch.cat([sp, fl])
    n = torch.cat([d, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand_as(fl)])
    w = torch.cat([torch.full((len(sp),), ball_weight, dtype=torch.float64), torch.ones(len(fl), dtype=torch.float64)])
    return p.to(device, dtype), n.to(device, dtype), w.to(device, dtype)


def _verts(field):
    chi = field.chi.detach().cpu().double().numpy()
    v, f, _, _ = marching_cubes(chi, 0.0)
    h = (field.upper[0] - field.lower[0]) / (chi.shape[0] - 1)
    return field.lower[0] + v * h, f, h


def test_local_level_gradcheck_float64(device):
    """Pass float64 gradcheck w.r.t. points, normals and weights with a local level."""
    g = torch.Generator().manual_seed(3)
    p = torch.rand(8, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    n = torch.randn(8, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    w = (0.5 + torch.rand(8, generator=g, dtype=torch.float64)).to(device).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a, b, c: poisson_indicator(a, b, c, 8, sigma=0.5, padding=0.1, level_sigma=1.5).chi, (p, n, w))


def test_closed_sphere_keeps_its_radius(device):
    """A closed surface takes one value of chi on it, so the local level recovers its radius as the global one."""
    g = torch.Generator().manual_seed(0)
    d = torch.randn(20000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    p, n = (0.5 + 0.3 * d).to(device), d.to(device)
    w = torch.ones(len(p), dtype=torch.float64, device=device)
    for ls in (0.0, 2.0):
        v, f, h = _verts(poisson_indicator(p, n, w, 48, sigma=1.0, padding=0.1, level_sigma=ls))
        assert len(f) > 1000
        assert np.abs(np.linalg.norm(v - 0.5, axis=1) - 0.3).max() < h


def test_open_sheet_beside_a_closed_part_stays_on_its_points(device):
    """A sheet the box cuts beside a closed sphere. With the sphere's points weighing as much as the sheet's,
    both levels keep the sheet; with them four times heavier one global level (mostly the sphere's) takes the
    sheet out of the mesh, as the fit's proxy lost a cut-open ground, while the local level keeps its crossing
    within a third of a cell of its points (with equal weights, at under half the global level's offset).
    The sphere stays within a cell and a half either way."""
    out = {}
    for ball_weight in (1.0, 4.0):
        p, n, w = _ball_on_floor(device=device, ball_weight=ball_weight)
        for ls in (0.0, 2.0):
            v, f, h = _verts(poisson_indicator(p, n, w, 64, sigma=1.0, padding=0.1, level_sigma=ls))
            # the sheet's part of the mesh: over the square's middle, away from the sphere's foot and the sides
            r = np.linalg.norm(v[:, :2] - BALL[0][:2], axis=1)
            mid = (r > BALL[1] + 4 * h) & np.all((v[:, :2] > 0.1) & (v[:, :2] < 0.9), axis=1)
            on = mid & (np.abs(v[:, 2] - FLOOR_Z) < 1.5 * h)
            out[ball_weight, ls] = (int(on.sum()), float(np.abs(v[on, 2] - FLOOR_Z).mean() / h) if on.any() else None)
            # the sphere's upper half (over it, near the domain's top, lies the sheet's periodic image)
            top = (v[:, 2] > BALL[0][2] + 0.05) & (v[:, 2] < BALL[0][2] + BALL[1] + 4 * h) & (r < BALL[1] + 4 * h)
            assert np.abs(np.linalg.norm(v[top] - BALL[0], axis=1) - BALL[1]).max() < 1.5 * h
    for ball_weight in (1.0, 4.0):
        count, err = out[ball_weight, 2.0]
        assert count > 500 and err < 0.3, out
    assert out[1.0, 0.0][0] > 500, out  # equal weights: the global level keeps the sheet too, a little off it
    assert out[1.0, 2.0][1] < 0.5 * out[1.0, 0.0][1], out
    assert out[4.0, 0.0][0] < 0.1 * out[4.0, 2.0][0], out  # a heavier closed part: it loses it


def test_local_level_empty_and_zero_weights(device):
    """No points or all-zero weights: chi = 0 and finite gradients, as with the global level."""
    p = torch.zeros(0, 3, device=device, requires_grad=True)
    field = poisson_indicator(p, torch.zeros(0, 3, device=device), torch.zeros(0, device=device), 16,
                              sigma=1.0, padding=0.1, level_sigma=2.0)
    assert (field.chi == 0).all()
    (gp,) = torch.autograd.grad(field.chi.sum(), p)
    assert gp.shape == (0, 3)
    g = torch.Generator().manual_seed(1)
    p = torch.rand(50, 3, generator=g).to(device).requires_grad_()
    w = torch.zeros(50, device=device, requires_grad=True)
    field = poisson_indicator(p, torch.randn(50, 3, generator=g).to(device), w, 16, sigma=1.0, padding=0.1,
                              level_sigma=2.0)
    assert (field.chi == 0).all()
    gp, gw = torch.autograd.grad((field.chi * torch.randn_like(field.chi)).sum(), (p, w))
    assert torch.isfinite(gp).all() and torch.isfinite(gw).all()


@pytest.mark.parametrize("case", ["one_voxel", "boundary", "huge_sigma", "tiny_weights"])
def test_local_level_stiff_cases_finite(device, case):
    """STABILITY's Poisson cases with a local level: all points in one voxel, points on the padded box's
    faces, a Gaussian wider than the grid, weights at 1e-30 (under the blend's floor): chi and its gradient finite."""
    g = torch.Generator().manual_seed(4)
    p = torch.rand(300, 3, generator=g, dtype=torch.float64)
    w = torch.ones(300, dtype=torch.float64)
    ls = 2.0
    if case == "one_voxel":
        p = 0.5 + 0.01 * p
    elif case == "boundary":
        p[:100, 0], p[100:200, 2] = -0.1, 1.1
    elif case == "huge_sigma":
        ls = 500.0
    else:
        w = w * 1e-30
    p = p.to(device).requires_grad_()
    n = torch.randn(300, 3, generator=g, dtype=torch.float64).to(device)
    field = poisson_indicator(p, n, w.to(device), 16, sigma=1.0, padding=0.1, level_sigma=ls)
    assert torch.isfinite(field.chi).all()
    (gp,) = torch.autograd.grad((field.chi * torch.randn_like(field.chi)).sum(), p)
    assert torch.isfinite(gp).all()
    if case != "tiny_weights":
        assert field.chi.abs().max() > 0 and gp.abs().sum() > 0


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_bad_level_sigma_raises(device, bad):
    """A negative or non-finite level_sigma raises ValueError naming it before any launch."""
    with pytest.raises(ValueError, match="level_sigma"):
        poisson_indicator(torch.rand(4, 3, device=device), torch.ones(4, 3, device=device),
                          torch.ones(4, device=device), 8, sigma=1.0, padding=0.1, level_sigma=bad)
