# SPDX-License-Identifier: Apache-2.0
"""Shared pieces of the rasterize_surfels tests (test_rasterize*.py): tolerances, the test camera, random
surfels, and renders and gradients compared with the brute-force reference."""

import torch
from reference.rasterize import rasterize_reference

import wtopo
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


def camera(width=37, height=29, distortion=None, skew=0.0):
    """The test camera (37 x 29 px by default) looking at the origin; with ``distortion`` or ``skew``, that
    lens, that skew and an off-centre principal point."""
    cam = wtopo.Camera.look_at([0.3, -0.2, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.9, width=width, height=height)
    if distortion is None and skew == 0.0:
        return cam
    K = cam.K.copy()
    K[0, 1] = skew
    K[0, 2] += 1.3  # off-centre principal point
    return wtopo.Camera(K, cam.world_to_camera, width, height, distortion)


def surfels(n, dtype=torch.float64, device="cpu", seed=0, sh=9, scale=(0.03, 0.3)):
    """``n`` random surfels, leaves requiring grad: ``[means, quats, scales, opacities, colors]`` with ``sh``
    SH coefficients per channel (0: plain RGB) and tangent scales drawn in ``scale``."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 2, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    ops = torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1
    cols = torch.randn(n, sh, 3, generator=g, dtype=dtype) * 0.4 if sh else torch.rand(n, 3, generator=g, dtype=dtype)
    return [t.to(device).requires_grad_(True) for t in (means, quats, scales, ops, cols)]


def render_both(params, cam, background=(0.1, 0.2, 0.3), **kw):
    """Render with rasterize_surfels and with the brute-force reference at the same near / far and filter
    width: ``(out, ref, shift)``, ``shift`` standing in for ``out.means2d`` in the reference."""
    out = rasterize_surfels(*params, cam, background=background, **kw)
    shift = torch.zeros(params[0].shape[0], 2, dtype=params[0].dtype, device=params[0].device, requires_grad=True)
    fs = kw["config"].filter_sigma if kw.get("config") is not None else RasterConfig().filter_sigma
    ref = rasterize_reference(*params, cam, near=out.near, far=out.far, background=background, shift=shift,
                              sh_degree=kw.get("sh_degree"), filter_sigma=fs)
    return out, ref, shift


def vjp(out, ref, params, shift, seed=1):
    """Gradients of both renders under the same random cotangents on every image: the kernel's w.r.t. the
    inputs and ``out.means2d``, the reference's w.r.t. the inputs and ``shift``."""
    g = torch.Generator().manual_seed(seed)
    ups = {k: torch.randn(ref[k].shape, generator=g, dtype=ref[k].dtype).to(ref[k].device) for k in IMAGES}
    lo = sum((getattr(out, k) * u).sum() for k, u in ups.items())
    lr = sum((ref[k] * u).sum() for k, u in ups.items())
    go = torch.autograd.grad(lo, [*params, out.means2d], allow_unused=True)
    gr = torch.autograd.grad(lr, [*params, shift], allow_unused=True)
    return go, gr


def assert_close(a, b, rtol=F64_RTOL, atol=F64_ATOL, name=""):
    """``torch.testing.assert_close`` on detached tensors, ``b`` cast to ``a``'s dtype, ``name`` in the message."""
    torch.testing.assert_close(a.detach(), b.detach().to(a.dtype), rtol=rtol, atol=atol, msg=lambda m: f"{name}: {m}")


def assert_forward(out, ref, rtol=F64_RTOL, atol=F64_ATOL):
    """Every image matches the reference within the tolerance, visibility exactly."""
    for k in IMAGES:
        assert_close(getattr(out, k), ref[k], rtol, atol, k)
    torch.testing.assert_close(out.visibility.long(), ref["visibility"])
