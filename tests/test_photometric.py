# SPDX-License-Identifier: Apache-2.0
"""photometric_loss (fused L1 + D-SSIM, separable window): values and gradients against the pure-torch
reference (full 2-D window), float64 finite differences, the fit's torch loss, and argument errors."""

import pytest
import torch
from reference.photometric import photometric_reference

from wtopo.ops import photometric_loss

# float64 Warp vs float64 reference: same maths, other summation order; observed <= 1e-15
F64_RTOL, F64_ATOL = 1e-10, 1e-12
# float32: sums of ~121 products per moment and the sxx = E[x^2] - mx^2 cancellation; observed ~1e-6
F32_RTOL, F32_ATOL = 1e-4, 1e-5
# float32 gradients relative to their largest entry (per-pixel values ~1 / (H W C)); observed <= 1e-5
F32_GRAD_REL = 1e-3
FD_EPS = 1e-6  # gradcheck step on images in [0.05, 0.95]: no |x - y| crosses 0 at this step


def _images(h, w, c=3, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, c, generator=g, dtype=dtype) * 0.9 + 0.05
    pred = (target + 0.15 * torch.randn(h, w, c, generator=g, dtype=dtype)).clamp(0.05, 0.95)
    return pred.to(device).requires_grad_(True), target.to(device)


# sizes straddle the window: exactly one valid position, a single valid row / column, non-square, odd
@pytest.mark.parametrize("size", [(11, 11), (11, 30), (29, 12), (40, 33)])
@pytest.mark.parametrize("dssim", [0.0, 0.2, 1.0])
def test_matches_reference_float64(device, size, dssim):
    """Match the full-window reference in value and gradient (float64)."""
    pred, target = _images(*size, device=device)
    got = photometric_loss(pred, target, dssim=dssim)
    want = photometric_reference(pred, target, dssim=dssim)
    torch.testing.assert_close(got, want, rtol=F64_RTOL, atol=F64_ATOL)
    (g_got,) = torch.autograd.grad(got, pred)
    (g_want,) = torch.autograd.grad(want, pred)
    torch.testing.assert_close(g_got, g_want, rtol=F64_RTOL, atol=F64_ATOL)
    assert g_got.abs().max() > 0  # the gradient was exercised


def test_matches_reference_float32(device):
    """Match the float64 reference in float32 (values and gradients)."""
    pred, target = _images(48, 37, device=device)
    p32 = pred.detach().float().requires_grad_(True)
    got = photometric_loss(p32, target.float())
    want = photometric_reference(pred, target)
    torch.testing.assert_close(got.double(), want, rtol=F32_RTOL, atol=F32_ATOL)
    (g32,) = torch.autograd.grad(got, p32)
    (g64,) = torch.autograd.grad(want, pred)
    err = (g32.double() - g64).abs().max() / g64.abs().max()
    assert err < F32_GRAD_REL, float(err)


def test_gradcheck_finite_differences(device):
    """Agree with float64 finite differences (torch.autograd.gradcheck), with a non-default window."""
    pred, target = _images(13, 15, c=2, device=device)

    def f(p):
        return photometric_loss(p, target, dssim=0.4, window=7, sigma=1.0)

    assert torch.autograd.gradcheck(f, (pred,), eps=FD_EPS, atol=1e-7, rtol=1e-5)


def test_equals_the_fits_torch_loss(device):
    """Equal the fit's CPU formulation ``(1 - w) L1 + w (1 - metrics.ssim)`` (float64)."""
    metrics = pytest.importorskip("wtopo.metrics")  # imports scipy (not on every GPU machine)
    pred, target = _images(31, 26, device=device)
    torch_loss = 0.8 * (pred - target).abs().mean() + 0.2 * (1.0 - metrics.ssim(pred, target))
    torch.testing.assert_close(photometric_loss(pred, target, dssim=0.2), torch_loss, rtol=F64_RTOL, atol=F64_ATOL)


def test_identical_images_and_flat_images(device):
    """Give 0 for identical images and stay finite on constant images (SSIM stabilisers)."""
    pred, target = _images(16, 16, device=device)
    same = photometric_loss(target.clone().requires_grad_(True), target)
    torch.testing.assert_close(same, torch.zeros((), dtype=torch.float64, device=device), rtol=0, atol=1e-12)
    flat = torch.full((16, 16, 3), 0.5, dtype=torch.float64, device=device, requires_grad=True)
    loss = photometric_loss(flat, torch.zeros_like(flat))
    (g,) = torch.autograd.grad(loss, flat)
    assert torch.isfinite(loss) and torch.isfinite(g).all()


def test_repeated_backward(device):
    """Give the same gradient on a second backward of the same graph (tape zeroed between)."""
    pred, target = _images(20, 18, device=device)
    loss = photometric_loss(pred, target)
    (a,) = torch.autograd.grad(loss, pred, retain_graph=True)
    (b,) = torch.autograd.grad(loss, pred)
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_validation_errors(device):
    """Raise TypeError / ValueError naming the argument before any launch."""
    pred, target = _images(16, 16, device=device)
    with pytest.raises(ValueError, match="target"):
        photometric_loss(pred, target[:, :15])
    with pytest.raises(TypeError, match="dtype"):
        photometric_loss(pred, target.float())
    with pytest.raises(ValueError, match="at least"):
        photometric_loss(pred[:10], target[:10])
    with pytest.raises(ValueError, match="window"):
        photometric_loss(pred, target, window=4)
    with pytest.raises(ValueError, match="dssim"):
        photometric_loss(pred, target, dssim=1.5)
    with pytest.raises(ValueError, match="pred"):
        photometric_loss(pred[0], target[0])
