# SPDX-License-Identifier: Apache-2.0
"""rasterize_surfels: forward and VJP against the brute-force torch reference, finite differences,
an analytic single surfel, distorted cameras, and the quaternion and opacity cases of design/stability.md
section 1 (its other cases: test_rasterize_stability.py; the fit's trusted path: test_rasterize_paths.py)."""

import math

import numpy as np
import pytest
import torch
from raster_cases import (
    F32_ATOL,
    F32_GRAD_REL,
    F32_RTOL,
    FD_EPS,
    IMAGES,
    assert_close,
    assert_forward,
    camera,
    render_both,
    surfels,
    vjp,
)
from reference.rasterize import rasterize_reference

import wtopo
from wtopo.ops import RasterConfig, rasterize_surfels


def _assert_vjp(out, ref, params, shift):
    """Every input gradient and means2d.grad match the reference in float64, each one exercised."""
    go, gr = vjp(out, ref, params, shift)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "means2d"), go, gr):
        assert float(b.abs().max()) > 0, name  # the gradient is exercised
        assert_close(a, b, name=name)


@pytest.mark.parametrize("sh", [0, 1, 9, 16], ids=["rgb", "sh0", "sh2", "sh3"])
def test_forward_and_vjp_match_reference(device, sh):
    """Match the brute-force reference (images, visibility, all input gradients, means2d.grad) in float64."""
    params = surfels(24, device=device, sh=sh)
    out, ref, shift = render_both(params, camera())
    assert int((out.alpha > 0).sum()) > 300  # coverage
    assert_forward(out, ref)
    assert_close(out.means2d, ref["means2d"], name="means2d")
    _assert_vjp(out, ref, params, shift)


@pytest.mark.parametrize("sigma", [0.2, 0.35, 1.5])
def test_filter_sigma_matches_reference(device, sigma):
    """A non-default low-pass width renders and differentiates like the reference, small surfels included."""
    # small surfels so that both branches occur at every width (all-filter would leave scales untested)
    params = surfels(24, device=device, seed=5, scale=(0.005, 0.06) if sigma < 1 else (0.03, 0.3))
    out, ref, shift = render_both(params, camera(), config=RasterConfig(filter_sigma=sigma))
    assert int((out.alpha > 0).sum()) > 30  # coverage (small surfels, narrow filter)
    assert_forward(out, ref)
    _assert_vjp(out, ref, params, shift)


@pytest.mark.parametrize("sigma", [0.35, 0.7071067811865476, 2.0])
def test_filter_sigma_footprint_is_analytic(device, sigma):
    """A tiny surfel at a pixel centre renders opacity * exp(-d^2 / (2 sigma^2)) at pixel distance d."""
    cam = camera(width=33, height=33)
    target = np.array([16.5, 16.5])  # the centre of pixel (16, 16)
    o, d = cam.pixel_rays("cpu", torch.float64)
    p = (o[16, 16] + 3.0 * d[16, 16]).reshape(1, 3)
    args = [p.to(device), torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64, device=device),
            torch.full((1, 2), 1e-7, dtype=torch.float64, device=device),
            torch.tensor([0.8], dtype=torch.float64, device=device),
            torch.ones(1, 3, dtype=torch.float64, device=device)]
    out = rasterize_surfels(*args, cam, config=RasterConfig(filter_sigma=sigma))
    np.testing.assert_allclose(cam.project(p.numpy())[0][0], target, atol=1e-9)
    a = out.alpha.detach().cpu().numpy()
    for di, dj in ((0, 0), (0, 1), (1, 1), (0, 2)):
        want = 0.8 * math.exp(-(di * di + dj * dj) / (2 * sigma**2))
        got = a[16 + di, 16 + dj]
        if want >= 1 / 255:
            assert abs(got - want) < 1e-9, (di, dj, got, want)
        else:
            assert got == 0.0, (di, dj, got)


def test_distorted_camera_matches_reference(device):
    """Render an OpenCV-distorted, skewed, off-centre camera exactly like the per-pixel-ray reference."""
    params = surfels(24, device=device, seed=3)
    cam = camera(distortion=[-0.25, 0.08, 0.01, -0.005, 0.01], skew=0.7)
    out, ref, shift = render_both(params, cam)
    plain = rasterize_surfels(*params, camera(), background=(0.1, 0.2, 0.3))
    assert float((out.rgb - plain.rgb).detach().abs().max()) > 0.05  # distortion really changed the image
    assert int((out.alpha > 0).sum()) > 300
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert float(b.abs().max()) > 0
        assert_close(a, b)


def test_float32_matches_float64_reference(device):
    """Agree in float32 with the float64 reference to float32 accuracy."""
    p64 = surfels(24, device=device, seed=5)
    p32 = [p.detach().float().requires_grad_(True) for p in p64]
    cam = camera()
    out = rasterize_surfels(*p32, cam, background=(0.1, 0.2, 0.3))
    ref = rasterize_reference(*p64, cam, near=out.near, far=out.far, background=(0.1, 0.2, 0.3))
    assert out.rgb.dtype == torch.float32 and int((out.alpha > 0).sum()) > 300
    for k in IMAGES:
        assert_close(getattr(out, k), ref[k], F32_RTOL, F32_ATOL, k)
    g = torch.Generator().manual_seed(2)
    ups = {k: torch.randn(ref[k].shape, generator=g, dtype=torch.float64).to(device) for k in IMAGES}
    g32 = torch.autograd.grad(sum((getattr(out, k) * u.float()).sum() for k, u in ups.items()), p32)
    g64 = torch.autograd.grad(sum((ref[k] * u).sum() for k, u in ups.items()), p64)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), g32, g64):
        scale = float(b.abs().max())
        assert scale > 0, name
        assert_close(a, b, 0.0, F32_GRAD_REL * scale, name)


def test_gradcheck_finite_differences(device):
    """Pass torch.autograd.gradcheck (float64, all differentiable inputs) on a small scene."""
    params = surfels(4, device=device, seed=7, sh=4, scale=(0.2, 0.4))
    cam = camera(13, 11)
    covered = rasterize_surfels(*params, cam).alpha.detach()
    assert int((covered > 0).sum()) > 40

    def f(*p):
        o = rasterize_surfels(*p, cam, background=(0.1, 0.2, 0.3), near=0.1, far=10.0)
        return o.rgb, o.alpha, o.depth, o.median_depth, o.normal, o.distortion * 100.0

    assert torch.autograd.gradcheck(f, params, eps=FD_EPS, atol=1e-5, rtol=1e-4)


def test_single_surfel_facing_camera_is_analytic(device):
    """Give alpha = opacity exp(-r^2 / 2) on the surfel's plane, depth = plane depth, flipped normal."""
    w, h, f, z0, s, op = 31, 27, 40.0, 2.0, 0.2, 0.8
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    cam = wtopo.Camera(K, np.eye(4), w, h)
    dt = torch.float64
    means = torch.tensor([[0.0, 0.0, z0]], dtype=dt, device=device)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=dt, device=device)
    scales = torch.tensor([[s, s]], dtype=dt, device=device)
    out = rasterize_surfels(means, quats, scales, torch.tensor([op], dtype=dt, device=device),
                            torch.tensor([[0.2, 0.5, 0.9]], dtype=dt, device=device), cam, background=[1.0, 1.0, 1.0])
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    r2 = (((j - w / 2) / f * z0) ** 2 + ((i - h / 2) / f * z0) ** 2) / s**2
    a = op * np.exp(-0.5 * r2)
    a[a < 1 / 255] = 0
    hit = a > 0
    np.testing.assert_allclose(out.alpha.cpu().numpy(), a, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.depth.cpu().numpy()[hit], z0, rtol=1e-12)
    np.testing.assert_allclose(out.median_depth.cpu().numpy()[hit], z0, rtol=1e-12)
    np.testing.assert_allclose(out.normal.cpu().numpy(), a[..., None] * np.array([0, 0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(out.rgb.cpu().numpy(), a[..., None] * [0.2, 0.5, 0.9] + (1 - a[..., None]), atol=1e-12)
    np.testing.assert_allclose(out.distortion.cpu().numpy(), 0.0, atol=1e-15)
    assert int(out.visibility[0]) == int(hit.sum()) > 50
    np.testing.assert_allclose(out.means2d.detach().cpu().numpy(), [[w / 2, h / 2]], atol=1e-12)
    assert out.radii[0] >= 3.4 * s * f / z0  # the alpha cut-off radius, sqrt(2 ln(255 op)) sigma, in pixels


# -- design/stability.md section 1: quaternions and opacity (the rest: test_rasterize_stability.py) --------


@pytest.mark.parametrize("norm", [1e3, 1e-3])
def test_quaternion_norm_is_irrelevant(device, norm):
    """Render non-unit quaternions like unit ones, with gradients orthogonal to q."""
    params = surfels(16, device=device, seed=17)
    unit = params[1].detach() / params[1].detach().norm(dim=1, keepdim=True)
    q = (unit * norm).requires_grad_(True)
    a = rasterize_surfels(params[0], unit, *params[2:], camera())
    b = rasterize_surfels(params[0], q, *params[2:], camera())
    for k in IMAGES:
        assert_close(getattr(b, k), getattr(a, k), name=k)
    (b.rgb.sum() + b.depth.sum()).backward()
    assert float(q.grad.abs().max()) > 0
    radial = (q.grad * q.detach()).sum(1).cpu().numpy()
    np.testing.assert_allclose(radial, 0.0, atol=1e-9 * float(q.grad.abs().max()) * norm)


def test_zero_quaternion_is_identity(device):
    """Treat a zero quaternion as the identity rotation, with a finite zero gradient."""
    params = surfels(3, device=device, seed=19)
    zero = torch.zeros(3, 4, dtype=torch.float64, device=device, requires_grad=True)
    ident = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64, device=device)
    a = rasterize_surfels(params[0], zero, *params[2:], camera())
    b = rasterize_surfels(params[0], ident, *params[2:], camera())
    assert int((a.alpha > 0).sum()) > 20
    assert_close(a.rgb, b.rgb)
    a.rgb.sum().backward()
    assert bool(torch.isfinite(zero.grad).all()) and float(zero.grad.abs().max()) == 0.0


def test_opacity_one_is_clamped(device):
    """Clamp alpha at 0.99 for opacity exactly 1."""
    params = surfels(1, device=device, seed=23, sh=0)
    with torch.no_grad():
        params[0][:] = torch.tensor([0.0, 0.0, 0.0])
        params[3][:] = 1.0
        params[2][:] = 0.5
    out = rasterize_surfels(*params, camera())
    assert abs(float(out.alpha.max()) - 0.99) < 1e-12
    out.rgb.sum().backward()
    assert bool(torch.isfinite(params[3].grad).all())


def test_two_views_rendered_before_one_backward(device):
    """Each render's backward reads the camera record of its own forward (a copy per call in device memory): two
    views rendered, then one backward through both, give the sum of each view's own gradients."""
    params = surfels(24, device=device)
    cams = [camera(), wtopo.Camera.look_at([0.8, 0.3, -2.6], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=37, height=29)]

    def grads(views):
        for p in params:
            p.grad = None
        outs = [rasterize_surfels(*params, c, sh_degree=2) for c in views]
        sum((o.rgb * o.rgb).sum() + o.depth.sum() for o in outs).backward()
        return [p.grad.clone() for p in params]

    both = grads(cams)
    alone = [grads([c]) for c in cams]
    for g, a, b in zip(both, *alone):
        assert float(a.abs().max()) > 0 and float(b.abs().max()) > 0
        assert_close(g, a + b)
