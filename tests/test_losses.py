# SPDX-License-Identifier: Apache-2.0
"""Loss terms of the fit: values on analytic cases and the design/stability.md section 7 cases."""

import math

import pytest
import torch

from wtopo.fitting import losses as L

# float32 results of a few roundings of O(1) values (the log or log1p of one pixel's depths; 1 - n.n of unit
# normals, each within 2 eps of exact, averaged): 8 eps bounds them (~9.5e-7)
TOL = 8 * torch.finfo(torch.float32).eps
GRADCHECK_EPS = 1e-6  # float64 finite-difference step (losses are smooth away from the masks)


def _rays(h, w, f=50.0, dtype=torch.float32):
    """Pinhole rays at the origin looking down +z, camera-z component 1."""
    j, i = torch.meshgrid(torch.arange(w, dtype=dtype) + 0.5, torch.arange(h, dtype=dtype) + 0.5, indexing="xy")
    d = torch.stack([(j - w / 2) / f, (i - h / 2) / f, torch.ones_like(j)], -1)
    return torch.zeros_like(d), d


def test_masked_mean_of_empty_mask_is_zero_with_finite_grad():
    """Return 0 (not NaN) for an empty mask and a zero gradient."""
    v = torch.randn(4, 5, requires_grad=True)
    out = L.masked_mean(v, torch.zeros(4, 5, dtype=torch.bool))
    out.backward()
    assert out.item() == 0.0
    assert torch.equal(v.grad, torch.zeros_like(v))


@pytest.mark.parametrize("form", ["log_ratio", "log1p_abs"])
def test_mesh_depth_loss_invalid_pixels_have_exactly_zero_grad(form):
    """Mask before the log: zero, negative and tiny depths outside the mask get gradient exactly 0."""
    ds = torch.tensor([[0.0, -1.0, 1e-12, 2.0]], requires_grad=True)
    dm = torch.tensor([[0.0, 3.0, -2.0, 2.5]], requires_grad=True)
    mask = torch.tensor([[False, False, False, True]])
    loss = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, form=form, extent=1.0)
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.equal(ds.grad[0, :3], torch.zeros(3)) and torch.equal(dm.grad[0, :3], torch.zeros(3))
    assert ds.grad[0, 3] != 0  # the valid pixel was exercised
    want = abs(math.log(2.0) - math.log(2.5)) if form == "log_ratio" else math.log1p(0.5)
    torch.testing.assert_close(loss, torch.tensor(want), atol=TOL, rtol=TOL)


def test_mesh_depth_loss_empty_mask_is_zero():
    """Return 0 when the surfel and mesh renders share no pixel."""
    ds = torch.rand(3, 3, requires_grad=True)
    loss = L.mesh_depth_loss(ds, torch.rand(3, 3), torch.zeros(3, 3, dtype=torch.bool), eps=1e-4)
    loss.backward()
    assert loss.item() == 0.0 and torch.isfinite(ds.grad).all()


def test_mesh_depth_loss_rejects_unknown_form():
    """Raise ValueError naming the form."""
    with pytest.raises(ValueError, match="form"):
        L.mesh_depth_loss(torch.ones(2), torch.ones(2), torch.ones(2, dtype=torch.bool), eps=1e-4, form="l2")


def test_mesh_depth_loss_gradcheck_float64():
    """Match finite differences in float64 on valid pixels."""
    ds = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    dm = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    mask = torch.rand(4, 4) > 0.3
    assert mask.any()
    assert torch.autograd.gradcheck(lambda a, b: L.mesh_depth_loss(a, b, mask, eps=1e-4), (ds, dm), eps=GRADCHECK_EPS)


@pytest.mark.parametrize("form", ["log_ratio", "log1p_abs"])
def test_mesh_depth_loss_debias_ignores_a_constant_offset(form):
    """Debiased, a proxy uniformly behind the surfels (log-ratio: by a factor; log1p: by a distance)
    costs what the same proxy without the offset costs, with the same gradient, and a shifted copy of
    the surfels costs nothing; without debias the offset adds its size."""
    ds = (torch.rand(6, 7, dtype=torch.float64) + 1.0).requires_grad_()
    shape = 1.0 + 0.1 * torch.rand(6, 7, dtype=torch.float64)
    mask = torch.rand(6, 7) > 0.2
    mask[0, 0] = True
    grads = []
    for dm in (ds.detach() * shape, ds.detach() * shape * 1.05) if form == "log_ratio" else \
            (ds.detach() + shape - 1, ds.detach() + shape - 1 + 0.05):
        ds.grad = None
        loss = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, form=form, debias=True)
        loss.backward()
        grads.append((loss.item(), ds.grad.clone()))
    assert grads[0][0] > 1e-3  # the shape difference was measured
    assert grads[1][0] == pytest.approx(grads[0][0], rel=1e-9)
    torch.testing.assert_close(grads[1][1], grads[0][1], atol=1e-12, rtol=1e-9)
    pull = grads[0][1] * (ds.detach() if form == "log_ratio" else 1.0)  # d loss / d log d_s for log-ratio
    assert pull[mask].sum().abs().item() < 1e-12  # no pull on the surfels as a whole
    copy = ds.detach() * 1.05 if form == "log_ratio" else ds.detach() + 0.05
    assert L.mesh_depth_loss(ds, copy, mask, eps=1e-4, form=form, debias=True).item() < 1e-12
    biased = L.mesh_depth_loss(ds, copy, mask, eps=1e-4, form=form)
    assert biased.item() == pytest.approx(math.log(1.05) if form == "log_ratio" else math.log1p(0.05), rel=1e-9)


def test_mesh_depth_loss_debias_keeps_shape_differences():
    """Debiased, a bump on one pixel still costs its size relative to the median and pulls that
    pixel's surfel depth towards the mesh; invalid pixels stay at zero gradient."""
    ds = torch.full((1, 6), 2.0, dtype=torch.float64, requires_grad=True)
    dm = torch.tensor([[2.2, 2.2, 2.2, 2.2, 3.0, 9.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, True, True, True, False]])
    loss = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, debias=True)
    loss.backward()
    # the median of the five log ratios is log(2 / 2.2); only the bump differs from it
    assert loss.item() == pytest.approx(math.log(3.0 / 2.2) / 5, rel=1e-9)
    assert ds.grad[0, 4] < 0  # descent moves the bump's surfel depth out towards the mesh
    assert ds.grad[0, 5] == 0


def test_mesh_depth_loss_debias_empty_mask_is_zero_and_gradcheck():
    """Empty mask: 0 with finite gradients (the median of nothing is taken as 0); non-empty: float64
    finite differences agree (the median is part of the loss, so its gradient is the true one)."""
    ds = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    dm = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    empty = L.mesh_depth_loss(ds, dm, torch.zeros(4, 4, dtype=torch.bool), eps=1e-4, debias=True)
    empty.backward()
    assert empty.item() == 0.0 and torch.isfinite(ds.grad).all()
    mask = torch.rand(4, 4) > 0.3
    assert mask.any()
    for form in ("log_ratio", "log1p_abs"):
        assert torch.autograd.gradcheck(
            lambda a, b, form=form: L.mesh_depth_loss(a, b, mask, eps=1e-4, form=form, debias=True), (ds, dm),
            eps=GRADCHECK_EPS)


def test_mesh_normal_loss_zero_normals_are_finite():
    """Zero rendered normals (zero alpha) give a finite loss and finite gradients, no NaN."""
    sn = torch.zeros(2, 2, 3, requires_grad=True)
    mn = torch.tensor([0.0, 0.0, 1.0]).expand(2, 2, 3)
    loss = L.mesh_normal_loss(sn, mn, torch.ones(2, 2, dtype=torch.bool))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(sn.grad).all()
    torch.testing.assert_close(loss, torch.tensor(1.0))


def test_mesh_normal_loss_ignores_mesh_orientation():
    """Agree with a face seen from either side (|cos|), and reach 1 for perpendicular normals."""
    sn = torch.tensor([[[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [1.0, 0.0, 0.0]]])
    mn = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]])
    m = torch.tensor([[True, True, False]])
    torch.testing.assert_close(L.mesh_normal_loss(sn, mn, m), torch.tensor(0.0))
    torch.testing.assert_close(L.mesh_normal_loss(sn, mn, torch.tensor([[False, False, True]])), torch.tensor(1.0))


def test_normal_consistency_is_zero_for_agreeing_normals():
    """Give 0 when the rendered normal equals the depth normal at full opacity."""
    n = torch.tensor([0.0, 0.6, -0.8]).expand(4, 4, 3)
    alpha = torch.ones(4, 4)
    out = L.normal_consistency(n, n, alpha, torch.ones(4, 4, dtype=torch.bool))
    torch.testing.assert_close(out, torch.tensor(0.0), atol=TOL, rtol=0)


def test_photometric_and_mask_loss_values():
    """Photometric loss is 0 for identical images; BCE is finite at alpha exactly 0 and 1."""
    img = torch.rand(16, 16, 3)
    torch.testing.assert_close(L.photometric(img, img, 0.2), torch.tensor(0.0), atol=1e-5, rtol=0)
    a = torch.tensor([[0.0, 1.0]], requires_grad=True)
    loss = L.mask_loss(a, torch.tensor([[True, False]]))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(a.grad).all() and loss > 1.0


# fused float32 loss vs the float64 torch formulation: observed <= 8e-9 on the value and <= 8e-7 of the
# largest gradient entry (per-pixel gradients ~1 / (H W C)); a 100x margin (float32 summation order)
PHOTO_ATOL = 1e-6
PHOTO_GRAD_REL = 1e-4


@pytest.mark.parametrize("size", [(128, 128), (11, 40), (8, 8)])
def test_photometric_is_the_torch_formulation(size):
    """Equal ``0.8 L1 + 0.2 (1 - metrics.ssim)`` in value and gradient on the CPU (the fused Warp loss; images
    under the SSIM window, L1 only, the torch path)."""
    from wtopo.metrics import ssim

    g = torch.Generator().manual_seed(1)
    target = torch.rand(*size, 3, generator=g)
    pred = (target + 0.1 * torch.randn(*size, 3, generator=g)).clamp(0, 1).requires_grad_(True)
    dssim = 0.2 if min(size) >= 11 else 0.0
    got = L.photometric(pred, target, dssim)
    p64, t64 = pred.detach().double().requires_grad_(True), target.double()
    want = (1 - dssim) * (p64 - t64).abs().mean() + (dssim * (1 - ssim(p64, t64)) if dssim else 0.0)
    torch.testing.assert_close(got.double(), want, atol=PHOTO_ATOL, rtol=0)
    (gg,) = torch.autograd.grad(got, pred)
    (gw,) = torch.autograd.grad(want, p64)
    err = float((gg.double() - gw).abs().max() / gw.abs().max())
    assert err < PHOTO_GRAD_REL, err


def test_scale_regularizer_two_and_three_axes():
    """Penalise anisotropy beyond the bound for 2 scales, the shortest axis for 3, 0 for none."""
    s2 = torch.tensor([[1.0, 1.0], [20.0, 1.0]])
    torch.testing.assert_close(L.scale_regularizer(s2, 10.0), torch.tensor(5.0))
    s3 = torch.tensor([[1.0, 2.0, 0.1], [0.3, 2.0, 3.0]])
    torch.testing.assert_close(L.scale_regularizer(s3, 10.0), torch.tensor(0.2))
    assert L.scale_regularizer(torch.zeros(0, 2), 10.0).item() == 0.0


def test_safe_normalize_keeps_zero_vectors_zero():
    """Normalise without NaN for zero vectors."""
    v = torch.zeros(3, 3, requires_grad=True)
    out = L.safe_normalize(v)
    out.sum().backward()
    assert torch.equal(out, torch.zeros(3, 3)) and torch.isfinite(v.grad).all()

