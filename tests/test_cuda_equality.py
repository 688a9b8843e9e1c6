# SPDX-License-Identifier: Apache-2.0
"""Every op gives the same forward values and input gradients on CUDA as on CPU (float64 unless stated).

Skipped without CUDA. Inputs are built on the CPU, copied to ``conftest.CUDA_DEVICE`` (``cuda:0``
unless ``WTOPO_TEST_CUDA`` names another), and each op is run forward
and backward (a fixed random upstream gradient) on both devices.
"""

import math

import numpy as np
import pytest
import torch
import trimesh
from conftest import CUDA_DEVICE as CUDA

import wtopo
from wtopo import ops

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

# float64, same arithmetic: CUDA differs by FMA contraction and by the order of float atomics
# (scatter, gradient accumulation); observed <= 1e-13 relative to each tensor's largest entry (H200)
F64_REL = 1e-10
# Poisson: cuFFT vs pocketfft on 32^3 grids, float64; observed ~1e-15 of the largest entry
FFT_REL = 1e-10
# the ray cast's BVH and hit search are float32 on both devices: depth/normal of the same face agree
# to float32 rounding of the hit point (~1e-7 relative)
RAY_F32_REL = 1e-5
# float32 rasterizer: the same float32 arithmetic up to FMA contraction and the atomics' order
F32_REL = 1e-4
F32_DISTORTION_ABS = 2e-6


def _close(a, b, rel, name=""):
    a = a.detach().cpu().to(torch.float64)
    b = b.detach().cpu().to(torch.float64)
    assert a.shape == b.shape, name
    scale = float(b.abs().max()) if b.numel() else 0.0
    torch.testing.assert_close(a, b, rtol=0, atol=rel * max(scale, 1e-30), msg=lambda m: f"{name}: {m}")


def _both(fn, inputs, outputs_for_grad, seed=0):
    """Run ``fn`` on CPU and CUDA copies of ``inputs``; return (outputs, input grads) per device."""
    res = {}
    for dev in ("cpu", CUDA):
        xs = [x.detach().to(dev).requires_grad_(x.requires_grad) for x in inputs]
        outs = fn(*xs)
        g = torch.Generator().manual_seed(seed)
        diff = [outs[i] for i in outputs_for_grad]
        ups = [torch.randn(o.shape, generator=g, dtype=o.dtype).to(dev) for o in diff]
        loss = sum((o * u).sum() for o, u in zip(diff, ups))
        need = [x for x in xs if x.requires_grad]
        grads = torch.autograd.grad(loss, need) if need else ()
        res[dev] = (outs, grads)
    return res["cpu"], res[CUDA]


def _surfels(n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 2, generator=g, dtype=dtype) * 0.2 + 0.03
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1
    cols = torch.randn(n, 4, 3, generator=g, dtype=dtype) * 0.4
    return [t.requires_grad_(True) for t in (means, quats, scales, opac, cols)]


def test_oriented_points_equal_on_cuda():
    """Give the same points, normals, weights and gradients on CUDA as on CPU."""
    means, quats, scales, opac, _ = _surfels(300)
    cpu, gpu = _both(lambda *p: tuple(ops.oriented_points(*p, samples=5)), [means, quats, scales, opac], [0, 1, 2])
    assert cpu[0][0].shape[0] == 1500
    for a, b in zip(gpu[0] + gpu[1], cpu[0] + cpu[1]):
        _close(a, b, F64_REL)


def test_scatter_and_sample_trilinear_equal_on_cuda():
    """Give the same scattered grid, sampled values and gradients on CUDA as on CPU (float atomics)."""
    g = torch.Generator().manual_seed(1)
    pts = (torch.rand(4000, 3, generator=g, dtype=torch.float64) * 0.98).requires_grad_(True)
    vals = torch.randn(4000, 2, generator=g, dtype=torch.float64).requires_grad_(True)
    cpu, gpu = _both(lambda p, v: (ops.scatter_trilinear(p, v, 24),), [pts, vals], [0])
    assert float(cpu[0][0].abs().sum()) > 0
    for a, b in zip(gpu[0] + gpu[1], cpu[0] + cpu[1]):
        _close(a, b, F64_REL)
    grid = torch.randn(20, 20, 20, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    cpu, gpu = _both(lambda gr, p: (ops.sample_trilinear(gr, p),), [grid, pts], [0])
    for a, b in zip(gpu[0] + gpu[1], cpu[0] + cpu[1]):
        _close(a, b, F64_REL)


def test_poisson_indicator_equal_on_cuda():
    """Give the same indicator (cuFFT vs pocketfft) and gradients on CUDA as on CPU."""
    g = torch.Generator().manual_seed(2)
    d = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    nrm = d / d.norm(dim=1, keepdim=True)
    pts = (0.5 + 0.3 * nrm).requires_grad_(True)
    w = torch.ones(2000, dtype=torch.float64).requires_grad_(True)
    nrm = nrm.clone().requires_grad_(True)
    cpu, gpu = _both(lambda p, n, ww: (ops.poisson_indicator(p, n, ww, 32, sigma=1.0, padding=0.1).chi,),
                     [pts, nrm, w], [0])
    assert float(cpu[0][0].min()) < 0 < float(cpu[0][0].max())
    for a, b in zip(gpu[0] + gpu[1], cpu[0] + cpu[1]):
        _close(a, b, FFT_REL)


def test_marching_cubes_equal_on_cuda():
    """Give the same vertices, the same faces and the same field gradient on CUDA as on CPU."""
    x = torch.linspace(-1, 1, 33, dtype=torch.float64)
    gx, gy, gz = torch.meshgrid(x, x, x, indexing="ij")
    field = ((gx**2 + gy**2 + gz**2).sqrt() - 0.6 + 0.05 * torch.sin(7 * gx) * torch.cos(5 * gy)).requires_grad_(True)
    cpu, gpu = _both(lambda f: ops.marching_cubes(f, 0.0, lower=(-1, -1, -1), upper=(1, 1, 1)), [field], [0])
    assert cpu[0][1].shape[0] > 1000
    assert torch.equal(gpu[0][1].cpu(), cpu[0][1])  # discrete: identical faces, same order
    _close(gpu[0][0], cpu[0][0], F64_REL, "verts")
    _close(gpu[1][0], cpu[1][0], F64_REL, "field grad")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rasterize_surfels_equal_on_cuda(dtype):
    """Give the same images, visibility and gradients (means2d included) on CUDA as on CPU."""
    params = [p.detach().to(dtype).requires_grad_(True) for p in _surfels(200, seed=3)]
    cam = wtopo.Camera.look_at([0.3, -0.2, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=64, height=48)
    res = {}
    for dev in ("cpu", CUDA):
        ps = [p.detach().to(dev).requires_grad_(True) for p in params]
        out = ops.rasterize_surfels(*ps, cam, background=(0.1, 0.2, 0.3))
        g = torch.Generator().manual_seed(4)
        imgs = [out.rgb, out.alpha, out.depth, out.median_depth, out.normal, out.distortion]
        loss = sum((im * torch.randn(im.shape, generator=g, dtype=dtype).to(dev)).sum() for im in imgs)
        grads = torch.autograd.grad(loss, [*ps, out.means2d])
        res[dev] = (imgs, grads, out.visibility, out.radii)
    (ic, gc, vc, rc), (ig, gg, vg, rg) = res["cpu"], res[CUDA]
    assert int((ic[1] > 0).sum()) > 1000
    assert torch.equal(vg.cpu(), vc) and torch.equal(rg.cpu(), rc)
    rel = F64_REL if dtype == torch.float64 else F32_REL
    failures = []
    names = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion", "means", "quats", "scales",
             "opacities", "colors", "means2d")
    for name, a, b in zip(names, ig + list(gg), ic + list(gc)):
        try:
            if dtype == torch.float32 and name == "distortion":
                # distortion sums O(1) terms m^2 (1 - T) + M2 - 2 m M1 that cancel to ~1e-5: absolute
                # float32 rounding of the terms (observed 2.3e-7 on an H200)
                torch.testing.assert_close(a.detach().cpu(), b.detach(), rtol=0, atol=F32_DISTORTION_ABS)
            else:
                _close(a, b, rel, name)
        except AssertionError as e:
            failures.append(str(e).splitlines()[0] + " " + " ".join(str(e).splitlines()[2:4]))
    assert not failures, "\n".join(failures)


def _mesh(device, dtype=torch.float64):
    m = trimesh.creation.icosphere(subdivisions=3)
    v = m.vertices * (1.0 + 0.1 * np.sin(3 * m.vertices[:, :1]))
    return torch.tensor(v, dtype=dtype, device=device), torch.tensor(m.faces, dtype=torch.int32, device=device)


def test_raycast_and_closest_faces_equal_on_cuda():
    """Hit the same faces with the same depth, normal and vertex gradient, and find the same closest faces."""
    cam = wtopo.Camera.look_at([0.4, 0.3, 3.0], [0, 0, 0], [0, -1, 0], fov_x=0.8, width=64, height=48)
    res = {}
    for dev in ("cpu", CUDA):
        v, f = _mesh(dev)
        v.requires_grad_(True)
        pts = torch.tensor(np.random.default_rng(6).normal(size=(500, 3)), dtype=v.dtype, device=dev)
        res[dev] = (v, ops.raycast_mesh(v, f, cam), ops.closest_faces(v.detach(), f, pts))
    (vc, oc, cc), (vg, og, cg) = res["cpu"], res[CUDA]
    assert int(oc.mask.sum()) > 500
    same = (og.face_id.cpu() == oc.face_id)
    # rays through a shared edge may pick either neighbour depending on float32 rounding
    assert float(same.float().mean()) > 0.995
    _close(og.depth.cpu()[same], oc.depth[same], RAY_F32_REL, "depth")
    _close(og.normal.cpu()[same], oc.normal[same], RAY_F32_REL, "normal")
    # vertex gradient of a loss seeded only on the pixels whose face agrees: it depends on those faces alone,
    # so both devices must agree on it even when a few edge rays picked different neighbours
    g = torch.Generator().manual_seed(5)
    up_depth = torch.randn(oc.depth.shape, generator=g, dtype=torch.float64) * same
    up_normal = torch.randn(oc.normal.shape, generator=g, dtype=torch.float64) * same[..., None]
    grads = []
    for v, out in ((vc, oc), (vg, og)):
        loss = (out.depth * up_depth.to(out.depth)).sum() + (out.normal * up_normal.to(out.normal)).sum()
        grads.append(torch.autograd.grad(loss, v)[0])
    assert int((grads[0].abs().sum(dim=1) > 0).sum()) > 100, "the gradient reached too few vertices"
    _close(grads[1], grads[0], RAY_F32_REL, "vertex grad")
    # the closest point is unique, its face is not when it lies on a shared edge or vertex (ties break
    # differently: 25 % of these points differ in face id on an H200), so points and distances are compared
    _close(cg[1], cc[1], RAY_F32_REL, "closest distance")
    _close(cg[2], cc[2], RAY_F32_REL, "closest point")
    assert math.isfinite(float(grads[1].abs().sum()))


def test_final_poisson_remesh_on_cuda_matches_the_cpu():
    """The fit's final watertight re-mesh on the fit's device: the same closed surface as on the CPU (float32
    Poisson, cuFFT against pocketfft: the vertices agree to float32 rounding of the level set)."""
    from test_final_mesh_repair import _open_sphere

    from wtopo.fitting import FitConfig
    from wtopo.fitting._final_mesh import poisson_remesh
    from wtopo.metrics import chamfer

    src = _open_sphere(subdivisions=4)
    cfg = FitConfig()
    cfg.final.resolution = 96
    events = []
    on_cuda = poisson_remesh(src, cfg, record=lambda e, **k: events.append(k), device=CUDA)
    on_cpu = poisson_remesh(src, cfg, record=lambda e, **k: None, device="cpu")
    assert events[-1]["device"] == CUDA and on_cuda.is_watertight and len(on_cuda.faces) > 1000
    assert chamfer(on_cuda, on_cpu).chamfer < 1e-4 * 0.66  # far below a cell (0.66 * 1.1 / 96 = 7.6e-3)
