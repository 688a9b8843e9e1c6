# SPDX-License-Identifier: Apache-2.0
"""oriented_points: forward and VJP against the torch reference, gradchecks, quaternion edge cases."""

import pytest
import torch
from reference.oriented_points import oriented_points_ref

from wtopo.ops import oriented_points

# float32 kernels vs the float32 torch reference: a handful of ulps on O(1) values.
ATOL_F32 = 1e-5
# float64: both sides round the same formulas; differences are at machine precision.
ATOL_F64 = 1e-12


def _surfels(n, dtype, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = 0.01 + torch.rand(n, 2, generator=g, dtype=dtype) * 0.1
    opac = torch.rand(n, generator=g, dtype=dtype)
    return [t.to(device).requires_grad_() for t in (means, quats, scales, opac)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("samples", [1, 5])
def test_forward_and_vjp_match_reference(device, dtype, samples):
    """Match the torch reference in value and in VJP for random upstream gradients."""
    inputs = _surfels(64, dtype, device)
    sign = torch.where(torch.rand(64) < 0.5, -1.0, 1.0).to(device, dtype)
    kw = dict(samples=samples, offset=0.7, opacity_threshold=0.3, center_weight=0.9, offset_weight=0.4,
              normal_sign=sign)
    out = oriented_points(*inputs, **kw)
    ref = oriented_points_ref(*inputs, **kw)
    atol = ATOL_F32 if dtype == torch.float32 else ATOL_F64
    ups = [torch.randn_like(r) for r in ref]
    assert (out.weights > 0).any() and (out.weights == 0).any()  # both sides of the threshold exercised
    for a, b in zip(out, ref):
        torch.testing.assert_close(a, b, atol=atol, rtol=0)
    ga = torch.autograd.grad(out, inputs, ups)
    gb = torch.autograd.grad(ref, inputs, ups, allow_unused=True)  # samples=1 does not use scales
    for a, b in zip(ga, gb):
        b = torch.zeros_like(a) if b is None else b
        assert b.abs().sum() > 0 or samples == 1
        torch.testing.assert_close(a, b, atol=atol * 10, rtol=0)
    torch.testing.assert_close(out.normals.norm(dim=1), torch.ones(64 * samples, dtype=dtype, device=device))


def test_gradcheck_float64(device):
    """Pass torch.autograd.gradcheck in float64 w.r.t. means, quats, scales, opacities."""
    inputs = _surfels(6, torch.float64, device, seed=1)
    fn = lambda *a: oriented_points(*a, opacity_threshold=0.2)  # noqa: E731
    assert torch.autograd.gradcheck(fn, tuple(inputs))


def test_identity_quaternion_samples_are_analytic(device):
    """Place the 4 offsets at mean +- offset*scale along x and y with the +z normal."""
    means = torch.tensor([[0.5, 0.5, 0.5]], device=device)
    quats = torch.tensor([[2.0, 0.0, 0.0, 0.0]], device=device)
    scales = torch.tensor([[0.2, 0.1]], device=device)
    out = oriented_points(means, quats, scales, torch.tensor([0.8], device=device))
    want = torch.tensor([[0.5, 0.5, 0.5], [0.6, 0.5, 0.5], [0.4, 0.5, 0.5], [0.5, 0.55, 0.5], [0.5, 0.45, 0.5]],
                        device=device)
    torch.testing.assert_close(out.points, want)
    torch.testing.assert_close(out.normals, torch.tensor([[0.0, 0.0, 1.0]], device=device).expand(5, 3))
    torch.testing.assert_close(out.weights, torch.tensor([0.8, 0.4, 0.4, 0.4, 0.4], device=device))


@pytest.mark.parametrize("norm", [1e-3, 1e3])
def test_unnormalised_quaternion_gives_same_result(device, norm):
    """Give the same points for q and norm*q, with a quaternion gradient orthogonal to q."""
    means, quats, scales, opac = _surfels(16, torch.float64, device, seed=2)
    a = oriented_points(means, quats, scales, opac)
    q2 = (quats.detach() * norm).requires_grad_()
    b = oriented_points(means, q2, scales, opac)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y)
    (g,) = torch.autograd.grad((b.points.sum() + b.normals.sum()), q2)
    assert g.abs().sum() > 0
    torch.testing.assert_close((g * q2).sum(1), torch.zeros(16, dtype=torch.float64, device=device), atol=1e-9, rtol=0)


def test_zero_quaternion_falls_back_to_identity(device):
    """Use the identity rotation for a zero quaternion, with a finite (zero) gradient."""
    means, quats, scales, opac = _surfels(3, torch.float32, device)
    q = quats.detach().clone()
    q[1] = 0
    q.requires_grad_()
    out = oriented_points(means, q, scales, opac)
    torch.testing.assert_close(out.normals[5:10], torch.tensor([[0.0, 0, 1]], device=device).expand(5, 3))
    (g,) = torch.autograd.grad(out.points.sum() + out.normals.sum(), q)
    assert torch.isfinite(g).all() and (g[1] == 0).all() and g[0].abs().sum() > 0


def test_below_threshold_weight_and_gradient_are_zero(device):
    """Give weight 0 and exactly zero opacity gradient below opacity_threshold."""
    means, quats, scales, _ = _surfels(2, torch.float32, device)
    opac = torch.tensor([0.1, 0.9], device=device, requires_grad=True)
    out = oriented_points(means, quats, scales, opac, opacity_threshold=0.5)
    assert (out.weights[:5] == 0).all() and (out.weights[5:] > 0).all()
    (g,) = torch.autograd.grad(out.weights.sum(), opac)
    torch.testing.assert_close(g, torch.tensor([0.0, 1.0 + 4 * 0.5], device=device))


def test_empty_input_gives_empty_outputs(device):
    """Return [0, 3] / [0] outputs and zero-size gradients for N = 0."""
    inputs = [torch.zeros(0, *s, device=device, requires_grad=True) for s in ((3,), (4,), (2,), ())]
    out = oriented_points(*inputs)
    assert out.points.shape == (0, 3) and out.normals.shape == (0, 3) and out.weights.shape == (0,)
    grads = torch.autograd.grad(out.points.sum() + out.weights.sum(), inputs)
    assert [g.shape for g in grads] == [t.shape for t in inputs]


@pytest.mark.parametrize("bad", ["nan_quat", "nan_mean", "samples", "sign", "shape", "dtype"])
def test_invalid_input_raises(device, bad):
    """Raise ValueError/TypeError naming the argument before any launch."""
    means, quats, scales, opac = (t.detach() for t in _surfels(4, torch.float32, device))
    kw = {}
    if bad == "nan_quat":
        quats[2, 1] = float("nan")
    elif bad == "nan_mean":
        means[3, 0] = float("inf")
    elif bad == "samples":
        kw["samples"] = 3
    elif bad == "sign":
        kw["normal_sign"] = torch.tensor([1.0, -1.0, 0.5, 1.0], device=device)
    elif bad == "shape":
        scales = scales[:, :1]
    elif bad == "dtype":
        opac = opac.double()
    name = {"nan_quat": "quats", "nan_mean": "means", "samples": "samples", "sign": "normal_sign",
            "shape": "scales", "dtype": "opacities"}[bad]
    with pytest.raises((ValueError, TypeError), match=name):
        oriented_points(means, quats, scales, opac, **kw)
