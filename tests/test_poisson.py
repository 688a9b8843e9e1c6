# SPDX-License-Identifier: Apache-2.0
"""poisson_indicator: reference, gradcheck, sphere recovery, padding, and the design/stability.md section 3/4 cases."""

import math

import numpy as np
import pytest
import torch
from reference.poisson import poisson_indicator_ref
from skimage.measure import marching_cubes

from wtopo.ops import oriented_points, poisson_indicator
from wtopo.poisson import PoissonContext


def _fft_tol(dtype, resolution: int, level_sigma: float, chi: torch.Tensor) -> float:
    """Absolute tolerance between two evaluations of chi that differ only in rounding: different FFT routines
    (``rfftn`` vs ``fftn``; batched vs one component at a time) and summation orders.

    An FFT of ``N`` values has an error of about ``eps * log2(N)`` relative to their magnitude; the solve runs
    two transforms (forward, inverse) and a local level (``level_sigma > 0``) two more (its blurred numerator
    and denominator), each bounded here by ``max |chi|``. Measured (CPU, 16^3, 300 points): float32 8.1e-6 at
    ``level_sigma = 0.7`` against this bound's 3.4e-5, 9.5e-7 without it against 1.5e-5; float64 1.4e-14
    against 5.4e-14.
    """
    transforms = 4 if level_sigma > 0 else 2
    return transforms * torch.finfo(dtype).eps * math.log2(resolution ** 3) * float(chi.detach().abs().max())


# fp32 vs fp64 of the op on a 32^3 sphere, relative to max |chi|: two float32 transforms of 32^3 values bound it
# by 2 * eps32 * log2(32^3) = 3.6e-6 (measured ~2e-6); STABILITY asks ~1e-5.
REL_F32_F64 = 1e-5


def _sphere(n, radius, centre=0.5, dtype=torch.float32, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    return (centre + radius * d).to(device, dtype), d.to(device, dtype)


def _radii(field, centre=0.5):
    chi = field.chi.detach().cpu().double().numpy()
    verts, faces, _, _ = marching_cubes(chi, 0.0)
    h = (field.upper[0] - field.lower[0]) / (chi.shape[0] - 1)
    verts = field.lower[0] + verts * h
    return np.linalg.norm(verts - centre, axis=1), verts, faces, h


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("resolution,level_sigma", [(8, 0.0), (9, 0.0), (16, 0.0), (8, 1.0), (9, 2.0), (16, 0.7)])
def test_forward_and_vjp_match_reference(device, dtype, resolution, level_sigma):
    """Match the pure-torch reference in chi and in the VJP w.r.t. points, normals, weights, with one global
    level and with a local one (``level_sigma``, which then changes the field)."""
    g = torch.Generator().manual_seed(resolution)
    p = torch.rand(40, 3, generator=g, dtype=dtype).to(device).requires_grad_()
    n = torch.randn(40, 3, generator=g, dtype=dtype).to(device).requires_grad_()
    w = torch.rand(40, generator=g, dtype=dtype).to(device).requires_grad_()
    out = poisson_indicator(p, n, w, resolution, sigma=0.7, padding=0.1, level_sigma=level_sigma).chi
    ref = poisson_indicator_ref(p, n, w, resolution, sigma=0.7, padding=0.1, level_sigma=level_sigma)
    if level_sigma > 0:
        assert (ref - poisson_indicator_ref(p, n, w, resolution, sigma=0.7, padding=0.1)).abs().max() > 1e-3
    torch.testing.assert_close(out, ref, atol=_fft_tol(dtype, resolution, level_sigma, ref), rtol=0)
    up = torch.randn_like(ref)
    ga = torch.autograd.grad(out, (p, n, w), up)
    gb = torch.autograd.grad(ref, (p, n, w), up)
    for a, b in zip(ga, gb):
        assert b.abs().sum() > 0
        # the backward runs the transforms again: twice the forward's rounding, relative to the gradient's size
        torch.testing.assert_close(a, b, atol=2 * _fft_tol(dtype, resolution, level_sigma, b), rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("resolution,level_sigma", [(9, 0.0), (16, 0.0), (16, 0.7)])
def test_the_field_without_gradients_is_the_field_with_them(device, dtype, resolution, level_sigma):
    """With nothing to differentiate the solve transforms one normal component at a time (a third of the
    memory of the final re-mesh at 768^3): the same field as the differentiable path, within float rounding
    (pocketfft's batched and single transforms differ in the last bits of float64), and the reference's."""
    g = torch.Generator().manual_seed(resolution + 1)
    p = torch.rand(300, 3, generator=g, dtype=dtype).to(device)
    n = torch.randn(300, 3, generator=g, dtype=dtype).to(device)
    w = torch.rand(300, generator=g, dtype=dtype).to(device)
    with torch.no_grad():
        plain = poisson_indicator(p, n, w, resolution, sigma=0.7, padding=0.1, level_sigma=level_sigma).chi
    diff = poisson_indicator(p.clone().requires_grad_(), n, w, resolution, sigma=0.7, padding=0.1,
                             level_sigma=level_sigma).chi
    assert diff.requires_grad and not plain.requires_grad and plain.abs().max() > 0.5
    tol = _fft_tol(dtype, resolution, level_sigma, plain)
    torch.testing.assert_close(plain, diff.detach(), atol=tol, rtol=0)
    ref = poisson_indicator_ref(p, n, w, resolution, sigma=0.7, padding=0.1, level_sigma=level_sigma)
    torch.testing.assert_close(plain, ref, atol=tol, rtol=0)


def test_gradcheck_float64(device):
    """Pass float64 gradcheck w.r.t. points, normals and weights on an 8^3 grid."""
    g = torch.Generator().manual_seed(1)
    p = torch.rand(8, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    n = torch.randn(8, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    w = (0.5 + torch.rand(8, generator=g, dtype=torch.float64)).to(device).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: poisson_indicator(a, b, c, 8, sigma=0.5, padding=0.1).chi,
                                    (p, n, w))


@pytest.mark.parametrize("resolution", [32, 48])
@pytest.mark.parametrize("radius", [0.3, 0.49])
def test_sphere_radius_recovered_within_one_voxel(device, resolution, radius):
    """Recover a sphere's radius within one voxel from points sampled on it (inside negative)."""
    p, n = _sphere(20_000, radius, device=device)
    field = poisson_indicator(p, n, torch.ones(len(p), device=device), resolution, sigma=1.0, padding=0.1)
    rad, verts, faces, h = _radii(field)
    assert len(faces) > 100
    assert np.abs(rad - radius).max() < h
    assert field.chi[resolution // 2, resolution // 2, resolution // 2] < 0


def test_sphere_049_does_not_leak(device):
    """Keep a radius-0.49 sphere from leaking across the periodic boundary: chi > 0 on the whole box shell."""
    r = 32
    p, n = _sphere(20_000, 0.49, device=device)
    field = poisson_indicator(p, n, torch.ones(len(p), device=device), r, sigma=1.0, padding=0.1)
    chi = field.chi
    shell = torch.cat([chi[0].flatten(), chi[-1].flatten(), chi[:, 0].flatten(), chi[:, -1].flatten(),
                       chi[:, :, 0].flatten(), chi[:, :, -1].flatten()])
    assert (shell > 0).all()
    _, verts, _, h = _radii(field)
    assert verts.min() > 0.01 - h and verts.max() < 0.99 + h


def test_fp32_matches_fp64(device):
    """Agree between float32 and float64 within ~1e-5 relative on chi."""
    p, n = _sphere(5000, 0.3, dtype=torch.float64, device=device)
    w = torch.ones(len(p), dtype=torch.float64, device=device)
    c64 = poisson_indicator(p, n, w, 32, sigma=1.0, padding=0.1).chi
    c32 = poisson_indicator(p.float(), n.float(), w.float(), 32, sigma=1.0, padding=0.1).chi
    err = (c32.double() - c64).abs().max() / c64.abs().max()
    assert err < REL_F32_F64


def test_empty_and_zero_weight_sets_give_zero_field(device):
    """Return chi = 0 (no NaN) and finite zero-size / zero gradients for no points or all-zero weights."""
    p = torch.zeros(0, 3, device=device, requires_grad=True)
    field = poisson_indicator(p, torch.zeros(0, 3, device=device), torch.zeros(0, device=device), 16,
                              sigma=1.0, padding=0.1)
    assert field.chi.shape == (16, 16, 16) and (field.chi == 0).all()
    (gp,) = torch.autograd.grad(field.chi.sum(), p)
    assert gp.shape == (0, 3)
    p, n = _sphere(100, 0.3, device=device)
    p.requires_grad_()
    w = torch.zeros(100, device=device, requires_grad=True)
    field = poisson_indicator(p, n, w, 16, sigma=1.0, padding=0.1)
    assert (field.chi == 0).all()
    gp, gw = torch.autograd.grad((field.chi * torch.randn_like(field.chi)).sum(), (p, w))
    assert torch.isfinite(gp).all() and torch.isfinite(gw).all()


def test_zero_normals_contribute_nothing_and_nan_normals_raise(device):
    """Ignore zero-length normals (same chi as without those points); raise on NaN normals."""
    p, n = _sphere(2000, 0.3, device=device, dtype=torch.float64)
    w = torch.ones(2000, dtype=torch.float64, device=device)
    extra = torch.rand(50, 3, dtype=torch.float64, device=device) * 0.2 + 0.4
    base = poisson_indicator(p, n, w, 16, sigma=1.0, padding=0.1).chi
    # Extra zero-normal points change nothing but the weighted level; give them zero weight.
    with_zero = poisson_indicator(torch.cat([p, extra]), torch.cat([n, torch.zeros_like(extra)]),
                                  torch.cat([w, torch.zeros(50, dtype=torch.float64, device=device)]), 16,
                                  sigma=1.0, padding=0.1).chi
    torch.testing.assert_close(base, with_zero, atol=1e-12, rtol=0)
    n_bad = n.clone()
    n_bad[7, 2] = float("nan")
    with pytest.raises(ValueError, match=r"normals.*\[7, 2\]"):
        poisson_indicator(p, n_bad, w, 16, sigma=1.0, padding=0.1)


@pytest.mark.parametrize("padding", [0.0, 0.1])
def test_points_on_boundary_are_finite(device, padding):
    """Accept points exactly on the faces of the unit cube (and of the padded box) with finite output."""
    g = torch.Generator().manual_seed(2)
    p = torch.rand(200, 3, generator=g, dtype=torch.float64)
    p[:50, 0] = 0.0
    p[50:100, 1] = 1.0
    p[100:110] = 1.0 + padding
    p[110:120] = -padding
    p = p.to(device).requires_grad_()
    n = torch.randn(200, 3, generator=g, dtype=torch.float64).to(device)
    field = poisson_indicator(p, n, torch.ones(200, dtype=torch.float64, device=device), 16, sigma=1.0,
                              padding=padding)
    assert torch.isfinite(field.chi).all() and field.chi.abs().max() > 0
    (gp,) = torch.autograd.grad((field.chi * torch.randn_like(field.chi)).sum(), p)
    assert torch.isfinite(gp).all() and gp.abs().sum() > 0


@pytest.mark.parametrize("value", [-0.2, 1.2, float("nan")])
def test_points_outside_padded_box_raise(device, value):
    """Raise ValueError naming the index of a point outside [-padding, 1 + padding]."""
    p = torch.full((4, 3), 0.5, device=device)
    p[2, 0] = value
    with pytest.raises(ValueError, match=r"points.*\[2, 0\]"):
        poisson_indicator(p, torch.ones(4, 3, device=device), torch.ones(4, device=device), 8, sigma=1.0,
                          padding=0.1)


@pytest.mark.parametrize("bad", ["weights", "resolution", "sigma", "padding", "dtype"])
def test_invalid_arguments_raise(device, bad):
    """Raise ValueError/TypeError naming the argument."""
    p = torch.rand(4, 3, device=device)
    n = torch.ones(4, 3, device=device)
    w = torch.ones(4, device=device)
    kw = dict(sigma=1.0, padding=0.1)
    r = 8
    if bad == "weights":
        w[1] = -1.0
    elif bad == "resolution":
        r = 3
    elif bad == "sigma":
        kw["sigma"] = -1.0
    elif bad == "padding":
        kw["padding"] = float("inf")
    else:
        n = n.double()
    with pytest.raises((ValueError, TypeError), match="normals" if bad == "dtype" else bad):
        poisson_indicator(p, n, w, r, **kw)


def test_all_points_in_one_voxel_finite(device):
    """Keep chi and gradients finite when every point falls in one voxel."""
    p = (0.5 + torch.rand(500, 3, dtype=torch.float64) * 0.01).to(device).requires_grad_()
    n = torch.randn(500, 3, dtype=torch.float64, device=device)
    field = poisson_indicator(p, n, torch.ones(500, dtype=torch.float64, device=device), 16, sigma=1.0,
                              padding=0.1)
    assert torch.isfinite(field.chi).all()
    (gp,) = torch.autograd.grad((field.chi * torch.randn_like(field.chi)).sum(), p)
    assert torch.isfinite(gp).all() and gp.abs().sum() > 0


@pytest.mark.parametrize("resolution", [8, 16, 24, 33])
@pytest.mark.parametrize("sigma", [0.0, 1.0, 50.0])
def test_resolutions_and_sigmas_are_finite(device, resolution, sigma):
    """Give a finite field, negative at the sphere centre unless smoothed flat, for any R and sigma."""
    p, n = _sphere(3000, 0.3, device=device)
    field = poisson_indicator(p, n, torch.ones(3000, device=device), resolution, sigma=sigma, padding=0.1)
    assert field.chi.shape == (resolution,) * 3
    assert torch.isfinite(field.chi).all()
    c = (resolution - 1) // 2
    if sigma <= 1.0:
        assert field.chi[c, c, c] < 0
    assert field.lower == (-0.1,) * 3 and field.upper == (1.1,) * 3


def test_context_caches_operators(device):
    """Reuse the spectral operator for the same resolution, sigma, device and dtype."""
    ctx = PoissonContext(max_entries=2)
    p, n = _sphere(100, 0.3, device=device)
    w = torch.ones(100, device=device)
    a = poisson_indicator(p, n, w, 16, sigma=1.0, padding=0.1, context=ctx).chi
    op = ctx.operator(16, 1.0, torch.device(device), torch.float32)
    b = poisson_indicator(p, n, w, 16, sigma=1.0, padding=0.1, context=ctx).chi
    assert ctx.operator(16, 1.0, torch.device(device), torch.float32) is op
    # CPU scatter is bitwise deterministic; CUDA atomics may reorder float sums (last bits only)
    tol = 0 if str(device) == "cpu" else 1e-5
    torch.testing.assert_close(a, b, atol=tol, rtol=tol)


def test_sphere_at_256_recovered(device):
    """Recover a sphere within one voxel at 256^3 (the production resolution), in bounded time."""
    p, n = _sphere(200_000, 0.35, device=device, seed=3)
    field = poisson_indicator(p, n, torch.ones(len(p), device=device), 256, sigma=2.0, padding=0.1)
    rad, _, faces, h = _radii(field)
    assert len(faces) > 10_000
    assert np.abs(rad - 0.35).max() < h


def test_chain_from_surfels_gradcheck_float64(device):
    """Pass float64 gradcheck through oriented_points -> poisson_indicator w.r.t. the surfel parameters."""
    g = torch.Generator().manual_seed(7)
    means = (0.3 + 0.4 * torch.rand(4, 3, generator=g, dtype=torch.float64)).to(device).requires_grad_()
    quats = torch.randn(4, 4, generator=g, dtype=torch.float64).to(device).requires_grad_()
    scales = (0.05 + 0.05 * torch.rand(4, 2, generator=g, dtype=torch.float64)).to(device).requires_grad_()
    opac = (0.5 + 0.5 * torch.rand(4, generator=g, dtype=torch.float64)).to(device).requires_grad_()

    def chain(m, q, s, o):
        pts = oriented_points(m, q, s, o)
        return poisson_indicator(pts.points, pts.normals, pts.weights, 8, sigma=0.5, padding=0.1).chi

    out = chain(means, quats, scales, opac)
    assert out.abs().max() > 0
    # fast_mode (random projections of the Jacobian) keeps this within seconds: 512 outputs x 40 inputs.
    assert torch.autograd.gradcheck(chain, (means, quats, scales, opac), fast_mode=True)


@pytest.mark.parametrize("resolution", [8, 9, 16, 17])
def test_spectral_solve_backward_is_the_adjoint_of_its_forward(device, resolution):
    """The solve's hand-written backward (the same solve with ``+i``) equals autograd through its forward's
    transforms, even and odd sizes (Nyquist bins), to float64 round-off."""
    from wtopo.poisson import _DEFAULT_CONTEXT, _SpectralSolve

    r = resolution
    wx, wy, wz, s = _DEFAULT_CONTEXT.operator(r, 0.7, torch.device(device), torch.float64)
    g = torch.Generator().manual_seed(r)
    v = torch.randn(r, r, r, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    up = torch.randn(r, r, r, generator=g, dtype=torch.float64).to(device)
    vh = torch.fft.rfftn(v.permute(3, 0, 1, 2), dim=(1, 2, 3))
    plain = torch.fft.irfftn(-1j * s * (wx * vh[0] + wy * vh[1] + wz * vh[2]), s=(r, r, r), dim=(0, 1, 2))
    mine = _SpectralSolve.apply(v, wx, wy, wz, s)
    torch.testing.assert_close(mine, plain, atol=1e-12, rtol=0)
    (ga,) = torch.autograd.grad(plain, v, up)
    (gb,) = torch.autograd.grad(mine, v, up)
    assert ga.abs().max() > 1e-3
    torch.testing.assert_close(gb, ga, atol=1e-12 * float(ga.abs().max()), rtol=0)
