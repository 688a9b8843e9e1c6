# SPDX-License-Identifier: Apache-2.0
"""The CPU per-tile pixel kernels (kernels/rasterize_tiles.py) against the per-pixel kernels they replace on
the CPU: the same images, discrete outputs and gradients bit for bit, in ordinary and stiff cases (the pixel
rectangles must be conservative wherever the tile binning is)."""

import pytest
import torch
from raster_cases import IMAGES, camera, surfels

from wtopo.ops import RasterConfig, rasterize_surfels
from wtopo.rasterize import _run


def _render_and_grads(params, cam, config, tiles: bool, monkeypatch):
    monkeypatch.setattr(_run, "CPU_TILE_KERNELS", tiles)
    out = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), config=config)
    g = torch.Generator().manual_seed(3)
    ups = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=out.rgb.dtype) for k in IMAGES}
    loss = sum((getattr(out, k) * u).sum() for k, u in ups.items())
    grads = torch.autograd.grad(loss, [*params, out.means2d], allow_unused=True) if params[0].shape[0] else ()
    return out, grads


def _stiff(kind: str, dtype):
    """Surfels of one stiff case (STABILITY.md sections 1 and 2) mixed with ordinary ones."""
    params = [p.detach().clone() for p in surfels(120, dtype=dtype, seed=2)]
    means, quats, scales, ops, cols = params
    if kind == "huge":  # larger than the frustum: every tile, every pixel
        scales[:3] = 1.0e4
    elif kind == "needle":  # anisotropy 1e6
        scales[:20, 0] = 0.3
        scales[:20, 1] = 3.0e-7
    elif kind == "tiny":  # the screen-space filter carries them
        scales[:40] = 1.0e-8
    elif kind == "edge-on":  # normals perpendicular to the view direction (+z towards the origin)
        quats[:40] = torch.tensor([0.7071067811865476, 0.7071067811865476, 0.0, 0.0], dtype=dtype)
    elif kind == "straddling-near":  # centres about the camera plane: some culled, some through the near plane
        means[:30, 2] = -2.9 + 0.2 * torch.linspace(-1, 1, 30, dtype=dtype)
        scales[:30] = 0.5
    elif kind == "transparent":  # opacity 0 skips, opacity 1 clamps to 0.99
        ops[:40] = 0.0
        ops[40:80] = 1.0
    return [p.requires_grad_(True) for p in params]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("tile_size", [8, 16])
@pytest.mark.parametrize("lens", ["pinhole", "distorted"])
def test_tile_kernels_equal_pixel_kernels(dtype, threads, tile_size, lens, monkeypatch):
    """Render and differentiate bit-identically with the per-tile and the per-pixel CPU kernels."""
    monkeypatch.setenv("WTOPO_NUM_THREADS", str(threads))
    dist = [-0.2, 0.05, 0.001, -0.002, 0.0] if lens == "distorted" else None
    cam = camera(width=45, height=29, distortion=dist, skew=2.0 if lens == "distorted" else 0.0)
    params = surfels(400, dtype=dtype, scale=(0.01, 0.12))
    cfg = RasterConfig(tile_size=tile_size)
    a, ga = _render_and_grads(params, cam, cfg, False, monkeypatch)
    b, gb = _render_and_grads(params, cam, cfg, True, monkeypatch)
    assert float(a.alpha.detach().max()) > 0.5 and int((a.visibility > 0).sum()) > 50  # the case is exercised
    for k in (*IMAGES, "visibility", "radii"):
        torch.testing.assert_close(getattr(b, k), getattr(a, k), rtol=0, atol=0, msg=k)
    for x, y in zip(gb, ga):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
        assert torch.isfinite(x).all()


@pytest.mark.parametrize("kind", ["huge", "needle", "tiny", "edge-on", "straddling-near", "transparent"])
def test_tile_kernels_equal_pixel_kernels_in_stiff_cases(kind, monkeypatch):
    """Keep the per-tile kernels bit-identical to the per-pixel ones for stiff surfels, finite throughout."""
    cam = camera()
    params = _stiff(kind, torch.float64)
    cfg = RasterConfig()
    a, ga = _render_and_grads(params, cam, cfg, False, monkeypatch)
    b, gb = _render_and_grads(params, cam, cfg, True, monkeypatch)
    assert int((a.visibility > 0).sum()) > 0
    for k in (*IMAGES, "visibility", "radii"):
        assert torch.isfinite(getattr(b, k).double()).all(), k
        torch.testing.assert_close(getattr(b, k), getattr(a, k), rtol=0, atol=0, msg=k)
    for x, y in zip(gb, ga):
        assert torch.isfinite(x).all()
        torch.testing.assert_close(x, y, rtol=0, atol=0)


@pytest.mark.parametrize("case", ["no-surfels", "all-culled"])
def test_tile_kernels_render_background_when_nothing_contributes(case, monkeypatch):
    """Give the background, zero alpha and zero gradients when no surfel reaches a pixel."""
    monkeypatch.setattr(_run, "CPU_TILE_KERNELS", True)
    cam = camera()
    params = surfels(0 if case == "no-surfels" else 50, dtype=torch.float32)
    if case == "all-culled":
        params = [p.detach().clone() for p in params]
        params[0][:, 2] -= 10.0  # every centre behind the camera
        params = [p.requires_grad_(True) for p in params]
    out = rasterize_surfels(*params, cam, background=(0.1, 0.2, 0.3), near=0.1, far=100.0)
    torch.testing.assert_close(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand_as(out.rgb))
    assert float(out.alpha.abs().max()) == 0.0
    if params[0].shape[0]:
        loss = sum(getattr(out, k).sum() for k in IMAGES)
        for gr in torch.autograd.grad(loss, params, allow_unused=True):
            assert gr is None or float(gr.abs().max()) == 0.0
