# SPDX-License-Identifier: Apache-2.0
"""rasterize_surfels: forward and VJP against the brute-force torch reference, finite differences,
an analytic single surfel, distorted cameras, and the design/stability.md sections 1 and 2 cases."""

import math

import numpy as np
import pytest
import torch
from reference.rasterize import rasterize_reference

import wtopo
from wtopo._profile import section
from wtopo.ops import RasterConfig, rasterize_surfels

IMAGES = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")
# float64 kernel vs float64 reference: same maths, different summation order; observed <= 1e-11
F64_RTOL, F64_ATOL = 1e-8, 1e-9
# float32 kernel vs float64 reference: observed ~1e-5 on colours/alpha; depth is in world units (~3)
F32_RTOL, F32_ATOL = 1e-3, 2e-3
# float32 gradients, relative to each gradient's largest entry: observed <= 3e-5 (float32 sums over ~1000 pixels)
F32_GRAD_REL = 2e-4
# ill-conditioned geometry (ray ~parallel to the plane, camera on the plane): t = -dot(a, n) / dot(d, n)
# amplifies rounding by ~1/angle; observed differences <= 1e-7 relative, so gradients get this slack
GRAZING_RTOL, GRAZING_ATOL = 1e-6, 1e-7
# camera on or inside a surfel plane: gradients reach ~1e8 through 1 / dot(a, n) with a.n ~ rounding, so
# their small entries carry the rounding of the large ones; CUDA (nvcc fuses multiply-adds into FMAs)
# differs from the reference by <= 2e-9 of the gradient's largest entry (H200), CPU by <= 3e-16
INSIDE_SCALE_REL = 1e-8
# repeated backward on CUDA: float atomics sum per-pixel contributions in a varying order (last bits);
# observed <= 3e-15 relative in float64 (H200). CPU sums per-worker buffers in a fixed order: exact.
CUDA_RERUN_RTOL, CUDA_RERUN_ATOL = 1e-12, 1e-12
FD_EPS = 1e-6  # gradcheck step: small enough not to cross the alpha cut-off or the branch switch


def _camera(width=37, height=29, distortion=None, skew=0.0):
    cam = wtopo.Camera.look_at([0.3, -0.2, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=width, height=height)
    if distortion is None and skew == 0.0:
        return cam
    K = cam.K.copy()
    K[0, 1] = skew
    K[0, 2] += 1.3  # off-centre principal point
    return wtopo.Camera(K, cam.world_to_camera, width, height, distortion)


def _surfels(n, dtype=torch.float64, device="cpu", seed=0, sh=9, scale=(0.03, 0.3)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 2, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    ops = torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1
    cols = torch.randn(n, sh, 3, generator=g, dtype=dtype) * 0.4 if sh else torch.rand(n, 3, generator=g, dtype=dtype)
    return [t.to(device).requires_grad_(True) for t in (means, quats, scales, ops, cols)]


def _render_both(params, cam, background=(0.1, 0.2, 0.3), **kw):
    out = rasterize_surfels(*params, cam, background=background, **kw)
    shift = torch.zeros(params[0].shape[0], 2, dtype=params[0].dtype, device=params[0].device, requires_grad=True)
    fs = kw["config"].filter_sigma if kw.get("config") is not None else RasterConfig().filter_sigma
    ref = rasterize_reference(*params, cam, near=out.near, far=out.far, background=background, shift=shift,
                              sh_degree=kw.get("sh_degree"), filter_sigma=fs)
    return out, ref, shift


def _vjp(out, ref, params, shift, seed=1):
    g = torch.Generator().manual_seed(seed)
    ups = {k: torch.randn(ref[k].shape, generator=g, dtype=ref[k].dtype).to(ref[k].device) for k in IMAGES}
    lo = sum((getattr(out, k) * u).sum() for k, u in ups.items())
    lr = sum((ref[k] * u).sum() for k, u in ups.items())
    go = torch.autograd.grad(lo, [*params, out.means2d], allow_unused=True)
    gr = torch.autograd.grad(lr, [*params, shift], allow_unused=True)
    return go, gr


def _assert_close(a, b, rtol=F64_RTOL, atol=F64_ATOL, name=""):
    torch.testing.assert_close(a.detach(), b.detach().to(a.dtype), rtol=rtol, atol=atol, msg=lambda m: f"{name}: {m}")


def _assert_vjp(out, ref, params, shift):
    """Every input gradient and means2d.grad match the reference in float64, each one exercised."""
    go, gr = _vjp(out, ref, params, shift)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "means2d"), go, gr):
        assert float(b.abs().max()) > 0, name  # the gradient is exercised
        _assert_close(a, b, name=name)


def _assert_forward(out, ref, rtol=F64_RTOL, atol=F64_ATOL):
    for k in IMAGES:
        _assert_close(getattr(out, k), ref[k], rtol, atol, k)
    torch.testing.assert_close(out.visibility.long(), ref["visibility"])


@pytest.mark.parametrize("sh", [0, 1, 9, 16], ids=["rgb", "sh0", "sh2", "sh3"])
def test_forward_and_vjp_match_reference(device, sh):
    """Match the brute-force reference (images, visibility, all input gradients, means2d.grad) in float64."""
    params = _surfels(24, device=device, sh=sh)
    out, ref, shift = _render_both(params, _camera())
    assert int((out.alpha > 0).sum()) > 300  # coverage
    _assert_forward(out, ref)
    _assert_close(out.means2d, ref["means2d"], name="means2d")
    _assert_vjp(out, ref, params, shift)


@pytest.mark.parametrize("sigma", [0.2, 0.35, 1.5])
def test_filter_sigma_matches_reference(device, sigma):
    """A non-default low-pass width renders and differentiates like the reference, small surfels included."""
    # small surfels so that both branches occur at every width (all-filter would leave scales untested)
    params = _surfels(24, device=device, seed=5, scale=(0.005, 0.06) if sigma < 1 else (0.03, 0.3))
    out, ref, shift = _render_both(params, _camera(), config=RasterConfig(filter_sigma=sigma))
    assert int((out.alpha > 0).sum()) > 30  # coverage (small surfels, narrow filter)
    _assert_forward(out, ref)
    _assert_vjp(out, ref, params, shift)


@pytest.mark.parametrize("sigma", [0.35, 0.7071067811865476, 2.0])
def test_filter_sigma_footprint_is_analytic(device, sigma):
    """A tiny surfel at a pixel centre renders opacity * exp(-d^2 / (2 sigma^2)) at pixel distance d."""
    cam = _camera(width=33, height=33)
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
    params = _surfels(24, device=device, seed=3)
    cam = _camera(distortion=[-0.25, 0.08, 0.01, -0.005, 0.01], skew=0.7)
    out, ref, shift = _render_both(params, cam)
    plain = rasterize_surfels(*params, _camera(), background=(0.1, 0.2, 0.3))
    assert float((out.rgb - plain.rgb).detach().abs().max()) > 0.05  # distortion really changed the image
    assert int((out.alpha > 0).sum()) > 300
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert float(b.abs().max()) > 0
        _assert_close(a, b)


def test_float32_matches_float64_reference(device):
    """Agree in float32 with the float64 reference to float32 accuracy."""
    p64 = _surfels(24, device=device, seed=5)
    p32 = [p.detach().float().requires_grad_(True) for p in p64]
    cam = _camera()
    out = rasterize_surfels(*p32, cam, background=(0.1, 0.2, 0.3))
    ref = rasterize_reference(*p64, cam, near=out.near, far=out.far, background=(0.1, 0.2, 0.3))
    assert out.rgb.dtype == torch.float32 and int((out.alpha > 0).sum()) > 300
    for k in IMAGES:
        _assert_close(getattr(out, k), ref[k], F32_RTOL, F32_ATOL, k)
    g = torch.Generator().manual_seed(2)
    ups = {k: torch.randn(ref[k].shape, generator=g, dtype=torch.float64).to(device) for k in IMAGES}
    g32 = torch.autograd.grad(sum((getattr(out, k) * u.float()).sum() for k, u in ups.items()), p32)
    g64 = torch.autograd.grad(sum((ref[k] * u).sum() for k, u in ups.items()), p64)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), g32, g64):
        scale = float(b.abs().max())
        assert scale > 0, name
        _assert_close(a, b, 0.0, F32_GRAD_REL * scale, name)


def test_gradcheck_finite_differences(device):
    """Pass torch.autograd.gradcheck (float64, all differentiable inputs) on a small scene."""
    params = _surfels(4, device=device, seed=7, sh=4, scale=(0.2, 0.4))
    cam = _camera(13, 11)
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


# -- design/stability.md section 1: surfel parameters ---------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tiny", [(1e-8, 1e-8), (1e-8, 0.1)], ids=["both", "one"])
def test_tiny_scales_render_through_the_filter(device, dtype, tiny):
    """Render 1e-8 scales with the screen-space filter: footprint >= a pixel, finite log-scale gradients."""
    params = _surfels(6, dtype=dtype, device=device, seed=11, sh=0)
    log_s = torch.log(torch.tensor(tiny, dtype=dtype, device=device)).repeat(6, 1).requires_grad_(True)
    out = rasterize_surfels(params[0], params[1], torch.exp(log_s), params[3], params[4], _camera())
    assert int((out.alpha > 0).sum()) >= 6  # each visible surfel covers at least its centre pixel
    loss = sum(getattr(out, k).sum() for k in IMAGES)
    grads = torch.autograd.grad(loss, [params[0], log_s, params[3]])
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    assert float(grads[0].abs().max()) > 0
    if dtype == torch.float64:
        ref = rasterize_reference(params[0], params[1], torch.exp(log_s), params[3], params[4], _camera(),
                                  near=out.near, far=out.far)
        _assert_forward(out, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_huge_scales_bounded_intersections(device, dtype):
    """Bin 1e4-scale surfels to at most every tile (no overflow) and render them finitely."""
    params = _surfels(5, dtype=dtype, device=device, seed=13, sh=0, scale=(1e4, 1e4))
    cam = _camera(40, 24)
    n_tiles = math.ceil(40 / 16) * math.ceil(24 / 16)
    out = rasterize_surfels(*params, cam, config=RasterConfig(tile_size=16, max_intersections=5 * n_tiles))
    assert bool(torch.isfinite(out.rgb).all()) and int((out.alpha > 0).sum()) == 40 * 24
    assert int(out.radii.max()) <= 1e9
    sum(getattr(out, k).sum() for k in IMAGES).backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in params)
    if dtype == torch.float64:
        ref = rasterize_reference(*params, cam, near=out.near, far=out.far)
        _assert_forward(out, ref)


def test_intersection_budget_raises(device):
    """Raise a clear ValueError when the tile intersections exceed config.max_intersections."""
    params = _surfels(30, device=device)
    with pytest.raises(ValueError, match="max_intersections"):
        rasterize_surfels(*params, _camera(), config=RasterConfig(max_intersections=10))


@pytest.mark.parametrize("norm", [1e3, 1e-3])
def test_quaternion_norm_is_irrelevant(device, norm):
    """Render non-unit quaternions like unit ones, with gradients orthogonal to q."""
    params = _surfels(16, device=device, seed=17)
    unit = params[1].detach() / params[1].detach().norm(dim=1, keepdim=True)
    q = (unit * norm).requires_grad_(True)
    a = rasterize_surfels(params[0], unit, *params[2:], _camera())
    b = rasterize_surfels(params[0], q, *params[2:], _camera())
    for k in IMAGES:
        _assert_close(getattr(b, k), getattr(a, k), name=k)
    (b.rgb.sum() + b.depth.sum()).backward()
    assert float(q.grad.abs().max()) > 0
    radial = (q.grad * q.detach()).sum(1).cpu().numpy()
    np.testing.assert_allclose(radial, 0.0, atol=1e-9 * float(q.grad.abs().max()) * norm)


def test_zero_quaternion_is_identity(device):
    """Treat a zero quaternion as the identity rotation, with a finite zero gradient."""
    params = _surfels(3, device=device, seed=19)
    zero = torch.zeros(3, 4, dtype=torch.float64, device=device, requires_grad=True)
    ident = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64, device=device)
    a = rasterize_surfels(params[0], zero, *params[2:], _camera())
    b = rasterize_surfels(params[0], ident, *params[2:], _camera())
    assert int((a.alpha > 0).sum()) > 20
    _assert_close(a.rgb, b.rgb)
    a.rgb.sum().backward()
    assert bool(torch.isfinite(zero.grad).all()) and float(zero.grad.abs().max()) == 0.0


def test_opacity_one_is_clamped(device):
    """Clamp alpha at 0.99 for opacity exactly 1."""
    params = _surfels(1, device=device, seed=23, sh=0)
    with torch.no_grad():
        params[0][:] = torch.tensor([0.0, 0.0, 0.0])
        params[3][:] = 1.0
        params[2][:] = 0.5
    out = rasterize_surfels(*params, _camera())
    assert abs(float(out.alpha.max()) - 0.99) < 1e-12
    out.rgb.sum().backward()
    assert bool(torch.isfinite(params[3].grad).all())


def _assert_background(out, params, bg, h, w):
    np.testing.assert_array_equal(out.rgb.detach().cpu().numpy(), np.broadcast_to(np.array(bg), (h, w, 3)))
    for k in ("alpha", "depth", "median_depth", "normal", "distortion"):
        assert float(getattr(out, k).detach().abs().max()) == 0.0, k
    loss = sum(getattr(out, k).sum() for k in IMAGES)
    if params[0].numel():
        grads = torch.autograd.grad(loss, params + [out.means2d])
    else:
        loss.backward()
        grads = [p.grad for p in params]
    for g, p in zip(grads, params):
        assert g is not None and g.shape == p.shape and int(torch.count_nonzero(g)) == 0


def test_zero_surfels(device):
    """Render N = 0 as the background with zero-size gradients of the right shapes."""
    params = [torch.zeros(0, *s, dtype=torch.float64, device=device, requires_grad=True)
              for s in ((3,), (4,), (2,), (), (3,))]
    out = rasterize_surfels(*params, _camera(), background=[0.3, 0.2, 0.1])
    assert out.visibility.shape == (0,) and out.radii.shape == (0,) and out.means2d.shape == (0, 2)
    _assert_background(out, params, [0.3, 0.2, 0.1], 29, 37)


def test_stages_are_profiler_sections(device):
    """Report binning, sort, forward and backward as ``wtopo._profile`` sections (benchmarks/bench_rasterize.py)."""
    params = _surfels(20, device=device, seed=5)
    times = {}
    with section("outside", add=lambda name, sec: times.__setitem__(name, times.get(name, 0.0) + sec)):
        rasterize_surfels(*params, _camera()).rgb.sum().backward()
    expected = {"outside", "rasterize_binning", "rasterize_sort", "rasterize_forward"}
    if torch.device(device).type == "cpu":  # CUDA: autograd runs the backward on its device thread, not collected
        expected.add("rasterize_backward")
    assert expected <= set(times), sorted(times)
    assert sum(times.values()) > 0


def test_all_culled(device):
    """Render surfels behind the camera, outside the frustum or before near as pure background."""
    params = _surfels(6, device=device, seed=29)
    with torch.no_grad():
        params[0][:3] = torch.tensor([0.3, -0.2, -3.0]) - torch.tensor([0.0, 0.0, 1.0]) * torch.arange(1, 4)[:, None]
        params[0][3:] = torch.tensor([[40.0, 0, 0], [0, 40, 0], [-40, 0, 0]])
    out = rasterize_surfels(*params, _camera(), near=0.5, far=10.0)
    assert int(out.visibility.sum()) == 0 and int(out.radii.max()) == 0
    _assert_background(out, params, [0.0, 0.0, 0.0], 29, 37)


def test_zero_opacity(device):
    """Render zero opacity as the background with gradients exactly 0 (no 0/0 from depth / alpha)."""
    params = _surfels(8, device=device, seed=31)
    with torch.no_grad():
        params[3][:] = 0.0
    out = rasterize_surfels(*params, _camera(), background=[0.5, 0.5, 0.5])
    _assert_background(out, params, [0.5, 0.5, 0.5], 29, 37)


# -- design/stability.md section 2: ray-surfel geometry --------------------------------------------------


def _edge_on(angle, device, offset=0.0):
    """One surfel at the origin whose plane makes ``angle`` (rad) with the viewing ray."""
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.6, width=21, height=17)
    half = 0.5 * (math.pi / 2 - angle)  # rotate the normal (+z, along the ray) by 90 deg - angle about y
    dt = torch.float64
    p = [torch.tensor([[offset, 0.0, 0.0]], dtype=dt), torch.tensor([[math.cos(half), 0, math.sin(half), 0]], dtype=dt),
         torch.tensor([[0.4, 0.25]], dtype=dt), torch.tensor([0.7], dtype=dt),
         torch.tensor([[0.9, 0.4, 0.1]], dtype=dt)]
    return cam, [t.to(device).requires_grad_(True) for t in p]


@pytest.mark.parametrize("angle", [0.3, 1e-3, 1e-5, 1e-7, 0.0])
def test_grazing_angles_match_reference(device, angle):
    """Render near-parallel surfels finitely and like the reference, gradients included."""
    cam, params = _edge_on(angle, device)
    out, ref, shift = _render_both(params, cam)
    assert int((out.alpha > 0).sum()) >= 3
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        _assert_close(a, b, GRAZING_RTOL, GRAZING_ATOL)


@pytest.mark.parametrize("angle", [0.2, 1e-4], ids=["surfel-side", "filter-side"])
def test_grazing_gradcheck_each_side_of_filter_switch(device, angle):
    """Pass finite differences with the object-space branch (0.2 rad) and with the filter branch (1e-4 rad)."""
    cam, params = _edge_on(angle, device, offset=0.013)

    def f(*p):
        o = rasterize_surfels(*p, cam, near=0.1, far=10.0)
        return o.rgb, o.alpha

    assert int((f(*params)[1] > 0).sum()) >= 3
    assert torch.autograd.gradcheck(f, params, eps=FD_EPS, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("where", ["on-plane", "inside", "at-centre"])
def test_camera_inside_surfel(device, where):
    """Keep outputs and gradients finite with the camera on a surfel plane, inside it, or at its centre."""
    cam = _camera()
    c = torch.tensor(cam.center, dtype=torch.float64)
    params = _surfels(4, device=device, seed=37, scale=(1.0, 2.0))
    with torch.no_grad():
        if where == "at-centre":
            params[0][0] = c
        else:
            fwd = torch.tensor(cam.forward, dtype=torch.float64)
            params[0][0] = c + (0.5 if where == "inside" else 2.0) * fwd
            # normal along the camera x axis: the camera centre lies in the plane
            ax = torch.tensor(cam.R[0], dtype=torch.float64)
            v = torch.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), ax, dim=0)
            ang = math.acos(float(ax[2]))
            params[1][0] = torch.cat([torch.tensor([math.cos(ang / 2)]), math.sin(ang / 2) * v / v.norm()])
    out, ref, shift = _render_both(params, cam)
    assert int((out.alpha > 0).sum()) > 50
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        _assert_close(a, b, GRAZING_RTOL, GRAZING_ATOL + INSIDE_SCALE_REL * float(b.abs().max()))


def test_straddling_near_plane_skips_pixels(device):
    """Skip only the pixels whose intersection is nearer than `near` for a surfel crossing the near plane."""
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=24, height=20)
    dt = torch.float64
    half = 0.5 * 1.3
    p = [torch.tensor([[0.0, 0.0, -1.0]], dtype=dt), torch.tensor([[math.cos(half), 0, math.sin(half), 0]], dtype=dt),
         torch.tensor([[3.0, 3.0]], dtype=dt), torch.tensor([0.9], dtype=dt), torch.tensor([[0.9, 0.4, 0.1]], dtype=dt)]
    params = [t.to(device).requires_grad_(True) for t in p]
    out, ref, shift = _render_both(params, cam, near=1.9, far=10.0)
    covered = int((out.alpha > 0).sum())
    assert 0 < covered < 24 * 20  # part of the surfel is cut by the near plane
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        _assert_close(a, b)


@pytest.mark.parametrize("size", [(1, 1), (17, 33), (31, 1), (16, 16), (33, 17)])
def test_odd_image_sizes(device, size):
    """Render 1x1, odd and non-multiple-of-tile images like the reference (border tiles initialised)."""
    w, h = size
    cam = wtopo.Camera.look_at([0.3, -0.2, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=w, height=h)
    params = _surfels(20, device=device, seed=41, scale=(0.2, 0.5))
    out, ref, shift = _render_both(params, cam)
    assert out.rgb.shape == (h, w, 3) and int((out.alpha > 0).sum()) >= 1
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        _assert_close(a, b)


def test_scene_scale_invariance(device):
    """Give identical images when the scene and camera are scaled by 1e-3 and 1e3 (default near/far)."""
    params = _surfels(24, device=device, seed=43)
    cam = _camera()
    base = rasterize_surfels(*params, cam)
    for k in (1e-3, 1e3):
        cam_k = cam.transformed(k, np.zeros(3))
        out = rasterize_surfels(params[0] * k, params[1], params[2] * k, params[3], params[4], cam_k)
        assert abs(out.near / base.near - k) < 1e-9 * k
        for name in ("rgb", "alpha", "normal", "distortion"):
            _assert_close(getattr(out, name), getattr(base, name), rtol=1e-6, atol=1e-9, name=name)
        _assert_close(out.depth, base.depth * k, rtol=1e-6, atol=1e-9 * k)


def test_cpu_worker_count_does_not_change_results(monkeypatch):
    """Give the same images and gradients with 1 and 3 CPU worker threads, bit-identical on reruns."""
    params = _surfels(40, seed=47)
    res = []
    for n in ("1", "3", "3"):
        monkeypatch.setenv("WTOPO_NUM_THREADS", n)
        out = rasterize_surfels(*params, _camera(67, 45), config=RasterConfig(tile_size=8, tiles_per_chunk=1))
        assert int((out.alpha > 0).sum()) > 1000
        grads = torch.autograd.grad(out.rgb.sum() + out.depth.sum(), params)
        res.append((out.rgb.detach(), out.visibility, grads))
    torch.testing.assert_close(res[0][0], res[1][0], rtol=0, atol=0)
    torch.testing.assert_close(res[0][1], res[1][1], rtol=0, atol=0)
    for a, b in zip(res[0][2], res[1][2]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)  # summation order differs
    for a, b in zip(res[1][2], res[2][2]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)  # fixed chunk-to-worker assignment


# warp-cooperative vs per-pixel CUDA kernels: the same per-pixel arithmetic (images and visibility exact);
# gradients are summed over a warp before one atomic instead of one atomic per pixel, a different order
# of float additions: float64 within CUDA_RERUN_*, float32 within the atomics' reordering tolerance of
# _assert_outputs_equal (H100: ~10 % of entries differ between reruns, by up to 1.1e-5)
COOP_F32_RTOL, COOP_F32_ATOL = 1e-3, 1e-4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: CPU launches never use warp cooperation")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tile_size", [8, 16, 32])
@pytest.mark.parametrize("batch", [1, 7, 32])  # 7: batches that end mid-list and mid-warp
def test_cooperative_warps_equal_per_pixel_kernels(monkeypatch, dtype, tile_size, batch):
    """Render and differentiate identically with and without warp-cooperative CUDA kernels."""
    from wtopo.rasterize import _run

    # 67 x 45: partial tiles on two edges at every tile size (their pixels walk with their warp)
    cam = _camera(67, 45)
    params = _surfels(400, dtype=dtype, device="cuda:0", seed=59)
    g = torch.Generator().manual_seed(5)
    res = []
    monkeypatch.setattr(_run, "PREFETCH_BATCH", batch)
    for coop in (False, True):
        monkeypatch.setattr(_run, "COOPERATIVE_WARPS", coop)
        out = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), config=RasterConfig(tile_size=tile_size))
        if not res:
            ups = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=dtype).to("cuda:0") for k in IMAGES}
        grads = torch.autograd.grad(sum((getattr(out, k) * u).sum() for k, u in ups.items()), [*params, out.means2d])
        res.append((out, grads))
    (a, ga), (b, gb) = res
    assert int((a.alpha > 0).sum()) > 1000
    for k in (*IMAGES, "visibility"):
        torch.testing.assert_close(getattr(b, k), getattr(a, k), rtol=0, atol=0, msg=k)
    tol = dict(rtol=CUDA_RERUN_RTOL, atol=CUDA_RERUN_ATOL) if dtype == torch.float64 else dict(
        rtol=COOP_F32_RTOL, atol=COOP_F32_ATOL)
    for x, y in zip(gb, ga):
        assert float(y.abs().max()) > 0
        torch.testing.assert_close(x, y, **tol)


def test_repeated_backward_is_stable(device):
    """Return identical gradients (CUDA: to atomics' reordering) when the same graph is differentiated twice."""
    params = _surfels(12, device=device, seed=53)
    out = rasterize_surfels(*params, _camera())
    loss = out.rgb.sum() + out.distortion.sum() + out.median_depth.sum()
    g1 = torch.autograd.grad(loss, params, retain_graph=True)
    g2 = torch.autograd.grad(loss, params)
    cuda = torch.device(device).type == "cuda"
    for a, b in zip(g1, g2):
        assert float(a.abs().max()) > 0
        if cuda:
            torch.testing.assert_close(a, b, rtol=CUDA_RERUN_RTOL, atol=CUDA_RERUN_ATOL)
        else:
            torch.testing.assert_close(a, b, rtol=0, atol=0)


# -- validation ----------------------------------------------------------------------------------


def test_validation_errors(device):
    """Raise TypeError/ValueError naming the argument before any launch."""
    params = _surfels(5, device=device)
    cam = _camera()
    bad = params[0].detach().clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"means.*\[3, 1\]"):
        rasterize_surfels(bad, *params[1:], cam)
    with pytest.raises(ValueError, match="quats"):
        rasterize_surfels(params[0], params[1][:, :3], *params[2:], cam)
    with pytest.raises(TypeError, match="scales"):
        rasterize_surfels(params[0], params[1], params[2].float(), *params[3:], cam)
    with pytest.raises(ValueError, match="opacities"):
        rasterize_surfels(*params[:3], params[3].detach() + 1.0, params[4], cam)
    with pytest.raises(ValueError, match="scales"):
        rasterize_surfels(params[0], params[1], -params[2].detach(), *params[3:], cam)
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize_surfels(*params, cam, sh_degree=3)
    with pytest.raises(ValueError, match="near"):
        rasterize_surfels(*params, cam, near=2.0, far=1.0)
    with pytest.raises(TypeError, match="camera"):
        rasterize_surfels(*params, "cam")
    with pytest.raises(ValueError, match="tile_size"):
        rasterize_surfels(*params, cam, config=RasterConfig(tile_size=12))
    for bad_sigma in (0.0, -1.0, float("nan"), 1e9):
        with pytest.raises(ValueError, match="filter_sigma"):
            rasterize_surfels(*params, cam, config=RasterConfig(filter_sigma=bad_sigma))


def test_edge_on_sweep_is_continuous(device):
    """Keep coverage continuous and finite while a surfel rotates from facing the camera to edge-on."""
    totals = []
    for deg in np.linspace(0.0, 90.0, 46):
        cam, params = _edge_on(math.radians(90.0 - deg), device)
        out = rasterize_surfels(*params, cam, near=0.1, far=10.0)
        assert bool(torch.isfinite(out.rgb).all()) and bool(torch.isfinite(out.depth).all())
        totals.append(float(out.alpha.detach().sum()))
    totals = np.array(totals)
    assert totals[-1] > 0  # the filter keeps an edge-on surfel visible
    assert np.all(np.abs(np.diff(totals)) <= 0.12 * totals.max()), np.round(totals, 2)
    assert np.all(np.diff(totals) <= 1e-9 * totals.max())  # foreshortening only shrinks the footprint


def test_needle_and_duplicates(device):
    """Render 1e6-anisotropy needles and duplicated surfels with finite values matching the reference."""
    params = _surfels(6, device=device, seed=59, sh=0)
    with torch.no_grad():
        params[2][:3] = torch.tensor([0.3, 0.3e-6])
        params[0][4] = params[0][5]
        params[1][4] = params[1][5]
    out, ref, shift = _render_both(params, _camera())
    assert int((out.alpha > 0).sum()) > 50 and int(out.radii.max()) < 1e9
    _assert_forward(out, ref)
    go, gr = _vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        _assert_close(a, b)


# -- the fit's trusted path: no validation, device-side clip defaults, deferred pair count -----------

def _trusted(params, cam, **kw):
    from wtopo.rasterize import _rasterize_trusted

    bg = torch.tensor([0.1, 0.2, 0.3], dtype=params[0].dtype, device=params[0].device)
    return _rasterize_trusted(*params, cam, sh_degree=None, background=bg, config=RasterConfig(), **kw)


def _assert_outputs_equal(a, b, params):
    """Every image, the discrete outputs and the VJP of two renders are bit-identical."""
    for k in (*IMAGES, "visibility", "radii"):
        torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=0, atol=0, msg=k)
    g = torch.Generator().manual_seed(3)
    ups = {k: torch.randn(getattr(a, k).shape, generator=g, dtype=a.rgb.dtype).to(a.rgb.device) for k in IMAGES}
    ga = torch.autograd.grad(sum((getattr(a, k) * u).sum() for k, u in ups.items()), params)
    gb = torch.autograd.grad(sum((getattr(b, k) * u).sum() for k, u in ups.items()), params)
    # CUDA sums the gradients with float atomics whose order varies from run to run (measured on an
    # H100: ~10 % of the entries differ, by up to 1.1e-5 in 1 of 5 runs); CPU sums are ordered
    tol = dict(rtol=1e-3, atol=1e-4) if a.rgb.is_cuda else dict(rtol=0, atol=0)
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y, **tol)


@pytest.mark.parametrize("device_clip", [False, True], ids=["host-clip", "device-clip"])
@pytest.mark.parametrize("defer_count", [False, True], ids=["exact-count", "deferred-count"])
def test_trusted_path_equals_public_path(device, device_clip, defer_count):
    """Render bit-identically through the fit's unchecked path, whichever clip and count mode it uses."""
    from wtopo.rasterize import _binning

    _binning._capacities.clear()
    cam = _camera()
    params = _surfels(300, dtype=torch.float32, device=device)
    for _ in range(2):  # the second deferred call uses the capacity the first one measured
        ref = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3))
        out = _trusted(params, cam, device_clip=device_clip, defer_count=defer_count)
        _assert_outputs_equal(out, ref, params)
    assert out.near == ref.near and out.far == ref.far
    if defer_count:
        assert not bool(out.overflow)
    else:
        assert out.overflow is None


@pytest.mark.parametrize("case", ["odd", "even", "none-in-front", "empty"])
def test_device_clip_defaults_equal_host_median(device, case):
    """Compute the default near / far on the device exactly as the host median does."""
    from wtopo.rasterize import _camera as C

    cam = _camera()
    n = {"odd": 301, "even": 300, "none-in-front": 50, "empty": 0}[case]
    means = _surfels(n, dtype=torch.float32, device=device)[0].detach()
    if case == "none-in-front":
        means = means - torch.tensor([0.0, 0.0, 10.0], device=device)  # every centre behind the camera
    cfg = RasterConfig()
    host = C._default_clip(means, cam, None, None, cfg)
    dev = C._default_clip_device(means, cam, cfg)
    assert dev.dtype == torch.float64
    assert tuple(dev.tolist()) == host


def _settle(cap, device):
    """Let the posted pair counts arrive (CUDA) and observe them; a no-op on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)
    cap.poll()


def test_deferred_count_overflow_then_growth(device):
    """Flag a view whose pairs exceed the kept capacity, then grow it: later calls equal fresh ones."""
    from wtopo import _bridge
    from wtopo.rasterize import _binning

    _binning._capacities.clear()
    cam = _camera()
    small = _surfels(40, dtype=torch.float32, device=device, scale=(0.01, 0.03))
    big = _surfels(800, dtype=torch.float32, device=device, seed=1)
    first = _trusted(small, cam, defer_count=True)  # sizes the capacity (one read)
    assert not bool(first.overflow)
    cap = _binning._pair_capacity(_bridge.warp_device(device))
    _settle(cap, device)  # CUDA posts the first count asynchronously: take it in before overriding it
    cap.value = 64  # as if earlier views had been tiny: the big one cannot fit
    over = _trusted(big, cam, defer_count=True)
    assert bool(over.overflow)
    assert torch.isfinite(over.rgb).all()  # incomplete, never out of bounds or NaN
    _settle(cap, device)
    again = _trusted(big, cam, defer_count=True)  # the overflowing count was observed: capacity grown
    assert not bool(again.overflow)
    assert cap.value >= _binning._CAPACITY_MIN
    _assert_outputs_equal(again, rasterize_surfels(*big, cam, background=(0.1, 0.2, 0.3)), big)
    # fewer surfels after more: same results as a fresh call with the larger buffers kept
    _assert_outputs_equal(_trusted(small, cam, defer_count=True),
                          rasterize_surfels(*small, cam, background=(0.1, 0.2, 0.3)), small)
