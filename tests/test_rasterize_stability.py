# SPDX-License-Identifier: Apache-2.0
"""rasterize_surfels in the design/stability.md sections 1 and 2 cases: tiny and huge scales, the intersection
budget, empty, culled and transparent scenes, grazing and edge-on surfels, the camera inside a surfel, the near
plane, odd image sizes, scene scale; then CPU worker counts, warp-cooperative CUDA kernels, repeated backward,
argument validation, needles and duplicates."""

import math

import numpy as np
import pytest
import torch
from raster_cases import (
    CUDA_RERUN_ATOL,
    CUDA_RERUN_RTOL,
    FD_EPS,
    GRAZING_ATOL,
    GRAZING_RTOL,
    IMAGES,
    INSIDE_SCALE_REL,
    assert_close,
    assert_forward,
    camera,
    render_both,
    surfels,
    vjp,
)
from reference.rasterize import rasterize_reference

import wtopo
from wtopo._profile import section
from wtopo.ops import RasterConfig, rasterize_surfels

# -- design/stability.md section 1: surfel parameters ---------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tiny", [(1e-8, 1e-8), (1e-8, 0.1)], ids=["both", "one"])
def test_tiny_scales_render_through_the_filter(device, dtype, tiny):
    """Render 1e-8 scales with the screen-space filter: footprint >= a pixel, finite log-scale gradients."""
    params = surfels(6, dtype=dtype, device=device, seed=11, sh=0)
    log_s = torch.log(torch.tensor(tiny, dtype=dtype, device=device)).repeat(6, 1).requires_grad_(True)
    out = rasterize_surfels(params[0], params[1], torch.exp(log_s), params[3], params[4], camera())
    assert int((out.alpha > 0).sum()) >= 6  # each visible surfel covers at least its centre pixel
    loss = sum(getattr(out, k).sum() for k in IMAGES)
    grads = torch.autograd.grad(loss, [params[0], log_s, params[3]])
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    assert float(grads[0].abs().max()) > 0
    if dtype == torch.float64:
        ref = rasterize_reference(params[0], params[1], torch.exp(log_s), params[3], params[4], camera(),
                                  near=out.near, far=out.far)
        assert_forward(out, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_huge_scales_bounded_intersections(device, dtype):
    """Bin 1e4-scale surfels to at most every tile (no overflow) and render them finitely."""
    params = surfels(5, dtype=dtype, device=device, seed=13, sh=0, scale=(1e4, 1e4))
    cam = camera(40, 24)
    n_tiles = math.ceil(40 / 16) * math.ceil(24 / 16)
    out = rasterize_surfels(*params, cam, config=RasterConfig(tile_size=16, max_intersections=5 * n_tiles))
    assert bool(torch.isfinite(out.rgb).all()) and int((out.alpha > 0).sum()) == 40 * 24
    assert int(out.radii.max()) <= 1e9
    sum(getattr(out, k).sum() for k in IMAGES).backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in params)
    if dtype == torch.float64:
        ref = rasterize_reference(*params, cam, near=out.near, far=out.far)
        assert_forward(out, ref)


def test_intersection_budget_raises(device):
    """Raise a clear ValueError when the tile intersections exceed config.max_intersections."""
    params = surfels(30, device=device)
    with pytest.raises(ValueError, match="max_intersections"):
        rasterize_surfels(*params, camera(), config=RasterConfig(max_intersections=10))



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
    out = rasterize_surfels(*params, camera(), background=[0.3, 0.2, 0.1])
    assert out.visibility.shape == (0,) and out.radii.shape == (0,) and out.means2d.shape == (0, 2)
    _assert_background(out, params, [0.3, 0.2, 0.1], 29, 37)


def test_stages_are_profiler_sections(device):
    """Report binning, sort, forward and backward as ``wtopo._profile`` sections (benchmarks/bench_rasterize.py)."""
    params = surfels(20, device=device, seed=5)
    times = {}
    with section("outside", add=lambda name, sec: times.__setitem__(name, times.get(name, 0.0) + sec)):
        rasterize_surfels(*params, camera()).rgb.sum().backward()
    expected = {"outside", "rasterize_binning", "rasterize_sort", "rasterize_forward"}
    if torch.device(device).type == "cpu":  # CUDA: autograd runs the backward on its device thread, not collected
        expected.add("rasterize_backward")
    assert expected <= set(times), sorted(times)
    assert sum(times.values()) > 0


def test_all_culled(device):
    """Render surfels behind the camera, outside the frustum or before near as pure background."""
    params = surfels(6, device=device, seed=29)
    with torch.no_grad():
        params[0][:3] = torch.tensor([0.3, -0.2, -3.0]) - torch.tensor([0.0, 0.0, 1.0]) * torch.arange(1, 4)[:, None]
        params[0][3:] = torch.tensor([[40.0, 0, 0], [0, 40, 0], [-40, 0, 0]])
    out = rasterize_surfels(*params, camera(), near=0.5, far=10.0)
    assert int(out.visibility.sum()) == 0 and int(out.radii.max()) == 0
    _assert_background(out, params, [0.0, 0.0, 0.0], 29, 37)


def test_zero_opacity(device):
    """Render zero opacity as the background with gradients exactly 0 (no 0/0 from depth / alpha)."""
    params = surfels(8, device=device, seed=31)
    with torch.no_grad():
        params[3][:] = 0.0
    out = rasterize_surfels(*params, camera(), background=[0.5, 0.5, 0.5])
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
    out, ref, shift = render_both(params, cam)
    assert int((out.alpha > 0).sum()) >= 3
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        assert_close(a, b, GRAZING_RTOL, GRAZING_ATOL)


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
    cam = camera()
    c = torch.tensor(cam.center, dtype=torch.float64)
    params = surfels(4, device=device, seed=37, scale=(1.0, 2.0))
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
    out, ref, shift = render_both(params, cam)
    assert int((out.alpha > 0).sum()) > 50
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        assert_close(a, b, GRAZING_RTOL, GRAZING_ATOL + INSIDE_SCALE_REL * float(b.abs().max()))


def test_straddling_near_plane_skips_pixels(device):
    """Skip only the pixels whose intersection is nearer than `near` for a surfel crossing the near plane."""
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=24, height=20)
    dt = torch.float64
    half = 0.5 * 1.3
    p = [torch.tensor([[0.0, 0.0, -1.0]], dtype=dt), torch.tensor([[math.cos(half), 0, math.sin(half), 0]], dtype=dt),
         torch.tensor([[3.0, 3.0]], dtype=dt), torch.tensor([0.9], dtype=dt), torch.tensor([[0.9, 0.4, 0.1]], dtype=dt)]
    params = [t.to(device).requires_grad_(True) for t in p]
    out, ref, shift = render_both(params, cam, near=1.9, far=10.0)
    covered = int((out.alpha > 0).sum())
    assert 0 < covered < 24 * 20  # part of the surfel is cut by the near plane
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert_close(a, b)


@pytest.mark.parametrize("size", [(1, 1), (17, 33), (31, 1), (16, 16), (33, 17)])
def test_odd_image_sizes(device, size):
    """Render 1x1, odd and non-multiple-of-tile images like the reference (border tiles initialised)."""
    w, h = size
    cam = wtopo.Camera.look_at([0.3, -0.2, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=w, height=h)
    params = surfels(20, device=device, seed=41, scale=(0.2, 0.5))
    out, ref, shift = render_both(params, cam)
    assert out.rgb.shape == (h, w, 3) and int((out.alpha > 0).sum()) >= 1
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert_close(a, b)


def test_scene_scale_invariance(device):
    """Give identical images when the scene and camera are scaled by 1e-3 and 1e3 (default near/far)."""
    params = surfels(24, device=device, seed=43)
    cam = camera()
    base = rasterize_surfels(*params, cam)
    for k in (1e-3, 1e3):
        cam_k = cam.transformed(k, np.zeros(3))
        out = rasterize_surfels(params[0] * k, params[1], params[2] * k, params[3], params[4], cam_k)
        assert abs(out.near / base.near - k) < 1e-9 * k
        for name in ("rgb", "alpha", "normal", "distortion"):
            assert_close(getattr(out, name), getattr(base, name), rtol=1e-6, atol=1e-9, name=name)
        assert_close(out.depth, base.depth * k, rtol=1e-6, atol=1e-9 * k)


def test_cpu_worker_count_does_not_change_results(monkeypatch):
    """Give the same images and gradients with 1 and 3 CPU worker threads, bit-identical on reruns."""
    params = surfels(40, seed=47)
    res = []
    for n in ("1", "3", "3"):
        monkeypatch.setenv("WTOPO_NUM_THREADS", n)
        out = rasterize_surfels(*params, camera(67, 45), config=RasterConfig(tile_size=8, tiles_per_chunk=1))
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
# _assert_outputs_equal in test_rasterize_paths.py (H100: ~10 % of entries differ between reruns, by up to 1.1e-5)
COOP_F32_RTOL, COOP_F32_ATOL = 1e-3, 1e-4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only: CPU launches never use warp cooperation")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tile_size", [8, 16, 32])
@pytest.mark.parametrize("batch", [1, 7, 32])  # 7: batches that end mid-list and mid-warp
def test_cooperative_warps_equal_per_pixel_kernels(monkeypatch, dtype, tile_size, batch):
    """Render and differentiate identically with and without warp-cooperative CUDA kernels."""
    from wtopo.rasterize import _run

    # 67 x 45: partial tiles on two edges at every tile size (their pixels walk with their warp)
    cam = camera(67, 45)
    params = surfels(400, dtype=dtype, device="cuda:0", seed=59)
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
    params = surfels(12, device=device, seed=53)
    out = rasterize_surfels(*params, camera())
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
    params = surfels(5, device=device)
    cam = camera()
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
    params = surfels(6, device=device, seed=59, sh=0)
    with torch.no_grad():
        params[2][:3] = torch.tensor([0.3, 0.3e-6])
        params[0][4] = params[0][5]
        params[1][4] = params[1][5]
    out, ref, shift = render_both(params, camera())
    assert int((out.alpha > 0).sum()) > 50 and int(out.radii.max()) < 1e9
    assert_forward(out, ref)
    go, gr = vjp(out, ref, params, shift)
    for a, b in zip(go, gr):
        assert bool(torch.isfinite(a).all())
        assert_close(a, b)
