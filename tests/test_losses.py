# SPDX-License-Identifier: Apache-2.0
"""Loss terms of the fit: values on analytic cases and the design/stability.md section 7 cases."""

import math

import numpy as np
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


def test_mesh_depth_loss_robust_cauchy_values_and_pull():
    """Robust (Cauchy) penalty ``s log1p(|diff| / s)``: about the plain absolute value where the two
    depths agree well within ``robust``, its pull on the surfel depth halved where they differ by
    exactly ``robust`` and a tenth of it at nine times ``robust``; ``log1p_abs`` with ``robust`` equal
    to ``extent`` is the plain form."""
    dm = torch.full((1, 3), 2.0, dtype=torch.float64)
    r = 0.01  # scene units: s = r / d_m = 0.005 in log units
    s = r / 2.0
    ds = (dm * torch.exp(torch.tensor([[1e-6, s, 9 * s]], dtype=torch.float64))).requires_grad_()
    mask = torch.ones(1, 3, dtype=torch.bool)
    per_pixel = []
    for k in range(3):
        one = torch.zeros_like(mask)
        one[0, k] = True
        ds.grad = None
        loss = L.mesh_depth_loss(ds, dm, one, eps=1e-4, robust=r)
        loss.backward()
        per_pixel.append((loss.item(), (ds.grad[0, k] * ds[0, k]).item()))  # d loss / d log d_s
    assert per_pixel[0][0] == pytest.approx(1e-6, rel=1e-3) and per_pixel[0][1] == pytest.approx(1.0, rel=1e-3)
    assert per_pixel[1][0] == pytest.approx(s * math.log(2.0), rel=1e-9)
    assert per_pixel[1][1] == pytest.approx(0.5, rel=1e-9)
    assert per_pixel[2][1] == pytest.approx(0.1, rel=1e-9)
    a = (torch.rand(3, 4, dtype=torch.float64) + 1.0)
    b = (torch.rand(3, 4, dtype=torch.float64) + 1.0)
    m = torch.rand(3, 4) > 0.3
    m[0, 0] = True
    plain = L.mesh_depth_loss(a, b, m, eps=1e-4, form="log1p_abs", extent=0.8)
    same = L.mesh_depth_loss(a, b, m, eps=1e-4, form="log1p_abs", extent=0.8, robust=0.8)
    assert plain.item() > 1e-3 and same.item() == pytest.approx(plain.item(), rel=1e-12)


def test_mesh_depth_loss_robust_gradcheck_and_empty_mask():
    """float64 finite differences agree for both forms, debiased or not (the per-pixel scale
    ``robust / d_m`` is part of the loss); an empty mask gives 0 with finite gradients."""
    ds = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    dm = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    empty = L.mesh_depth_loss(ds, dm, torch.zeros(4, 4, dtype=torch.bool), eps=1e-4, robust=0.05)
    empty.backward()
    assert empty.item() == 0.0 and torch.isfinite(ds.grad).all()
    mask = torch.rand(4, 4) > 0.3
    mask[0, 0] = True
    for form in ("log_ratio", "log1p_abs"):
        for debias in (False, True):
            assert torch.autograd.gradcheck(
                lambda a, b, form=form, debias=debias: L.mesh_depth_loss(a, b, mask, eps=1e-4, form=form,
                                                                          debias=debias, robust=0.05),
                (ds, dm), eps=GRADCHECK_EPS)


def test_mesh_depth_loss_robust_behind_applies_the_cauchy_form_only_behind_the_proxy():
    """``robust_behind``: a pixel where the surfels lie behind the proxy gets the Cauchy penalty and pull
    (``s log1p(|x| / s)``, pull ``1 / (1 + |x| / s)``), one in front the plain ``|x|`` and pull 1; without
    a robust scale the flag changes nothing; float64 finite differences agree for both forms, debiased
    or not."""
    dm = torch.full((1, 2), 2.0, dtype=torch.float64)
    ds = torch.tensor([[1.5, 2.6]], dtype=torch.float64, requires_grad=True)  # in front, behind
    mask = torch.ones(1, 2, dtype=torch.bool)
    r = 0.2
    s = r / 2.0  # the log-ratio form's scale: robust / d_m
    front, back = abs(math.log(1.5 / 2.0)), abs(math.log(2.6 / 2.0))
    loss = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, robust=r, robust_behind=True)
    (g,) = torch.autograd.grad(loss, ds)
    assert loss.item() == pytest.approx((front + s * math.log1p(back / s)) / 2, rel=1e-12)
    # d loss / d log d_s per pixel (the mean over two pixels halves it)
    assert (2 * g[0, 0] * 1.5).item() == pytest.approx(-1.0, rel=1e-12)
    assert (2 * g[0, 1] * 2.6).item() == pytest.approx(1.0 / (1.0 + back / s), rel=1e-12)
    two_sided = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, robust=r)
    plain = L.mesh_depth_loss(ds, dm, mask, eps=1e-4)
    assert two_sided.item() < loss.item() < plain.item()
    assert L.mesh_depth_loss(ds, dm, mask, eps=1e-4, robust_behind=True).item() == plain.item()
    a = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    b = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    m = torch.rand(4, 4) > 0.3
    m[0, 0] = True
    for form in ("log_ratio", "log1p_abs"):
        for debias in (False, True):
            assert torch.autograd.gradcheck(
                lambda x, y, form=form, debias=debias: L.mesh_depth_loss(x, y, m, eps=1e-4, form=form, debias=debias,
                                                                          robust=0.05, robust_behind=True),
                (a, b), eps=GRADCHECK_EPS)


def test_mesh_depth_loss_behind_weighs_only_surfels_behind_the_proxy():
    """``behind`` scales the penalty and the pull of the pixels where the surfel depth exceeds the
    proxy's (after the debias), leaves the pixels in front untouched, and 1 is the plain term; float64
    finite differences agree with ``behind`` below 1, debiased or not."""
    dm = torch.full((1, 2), 2.0, dtype=torch.float64)
    ds = torch.tensor([[1.8, 2.3]], dtype=torch.float64, requires_grad=True)  # in front, behind
    mask = torch.ones(1, 2, dtype=torch.bool)
    plain = L.mesh_depth_loss(ds, dm, mask, eps=1e-4)
    (g_plain,) = torch.autograd.grad(plain, ds)
    half = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, behind=0.25)
    (g_half,) = torch.autograd.grad(half, ds)
    front, back = abs(math.log(1.8 / 2.0)), abs(math.log(2.3 / 2.0))
    assert plain.item() == pytest.approx((front + back) / 2, rel=1e-12)
    assert half.item() == pytest.approx((front + 0.25 * back) / 2, rel=1e-12)
    assert g_half[0, 0].item() == pytest.approx(g_plain[0, 0].item(), rel=1e-12) and g_plain[0, 0] < 0
    assert g_half[0, 1].item() == pytest.approx(0.25 * g_plain[0, 1].item(), rel=1e-12) and g_plain[0, 1] > 0
    same = L.mesh_depth_loss(ds, dm, mask, eps=1e-4, behind=1.0)
    assert same.item() == plain.item()
    a = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    b = (torch.rand(4, 4, dtype=torch.float64) + 0.5).requires_grad_()
    m = torch.rand(4, 4) > 0.3
    m[0, 0] = True
    for debias in (False, True):
        assert torch.autograd.gradcheck(
            lambda x, y, debias=debias: L.mesh_depth_loss(x, y, m, eps=1e-4, debias=debias, behind=0.3),
            (a, b), eps=GRADCHECK_EPS)


def test_erode_removes_parts_narrower_than_its_square():
    """Erosion by a ``(2 w + 1)^2`` square: a 5 x 7 block keeps its 3 x 5 interior at w = 1 and its 1 x 3
    core at w = 2; a 3-pixel strip vanishes at w = 2; the image border does not erode; w = 0 is the mask;
    ``boundary_band`` is the dilation minus this erosion."""
    m = torch.zeros(12, 14, dtype=torch.bool)
    m[2:7, 3:10] = True  # 5 x 7 block
    m[9:12, :] = True  # 3-pixel strip along the bottom edge
    e1 = L.erode(m, 1)
    assert e1[3:6, 4:9].all() and int(e1[:8].sum()) == 15
    assert int(e1[8:].sum()) == 2 * 14 and e1[10:12].all()  # the strip keeps its rows that touch the border
    e2 = L.erode(m, 2)
    assert e2[4, 5:8].all() and int(e2[:8].sum()) == 3
    assert int(e2[8:].sum()) == 14 and e2[11].all()  # only the row on the border survives
    strip = torch.zeros(10, 10, dtype=torch.bool)
    strip[4:7, 1:9] = True
    assert not L.erode(strip, 2).any() and L.erode(strip, 1)[5, 2:8].all()
    assert torch.equal(L.erode(m, 0), m)
    band = L.boundary_band(m, 1)
    assert not (band & e1).any() and band[m & ~e1].all()


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


def test_depth_normals_of_a_tilted_plane():
    """Recover the normal of a plane z = 2 + 0.3 x, facing the camera, with zero borders."""
    o, d = _rays(16, 16)
    # ray x = d_x t, z = t: t = 2 / (1 - 0.3 d_x)
    depth = 2.0 / (1 - 0.3 * d[..., 0])
    n, m = L.depth_normals(depth, o, d, torch.ones(16, 16, dtype=torch.bool))
    want = torch.tensor([0.3, 0.0, -1.0]) / math.sqrt(1.09)
    assert m[1:-1, 1:-1].all() and not m[0].any() and not m[:, -1].any()
    torch.testing.assert_close(n[5, 5], want, atol=1e-4, rtol=0)
    assert torch.equal(n[0], torch.zeros(16, 3))


def test_depth_normals_at_discontinuities_are_finite_and_masked():
    """Invalid (zero) depth and jumps stay finite; invalid neighbours are masked out."""
    o, d = _rays(8, 8)
    depth = torch.ones(8, 8)
    depth[:, 4:] = 5.0
    depth[2, 2] = 0.0
    valid = depth > 0
    depth.requires_grad_()
    n, m = L.depth_normals(depth, o, d, valid)
    n.sum().backward()
    assert torch.isfinite(n).all() and torch.isfinite(depth.grad).all()
    assert not m[2, 2] and not m[1, 2] and not m[2, 1]


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


def test_boundary_band_is_the_ring_around_the_mask_edge():
    """A 6x6 square in a 12x12 image: width 1 gives the 8x8 ring minus the 4x4 core; 0 gives nothing."""
    m = torch.zeros(12, 12, dtype=torch.bool)
    m[3:9, 3:9] = True
    band = L.boundary_band(m, 1)
    want = torch.zeros(12, 12, dtype=torch.bool)
    want[2:10, 2:10] = True
    want[4:8, 4:8] = False
    assert torch.equal(band, want) and int(band.sum()) == 64 - 16
    assert int(L.boundary_band(m, 2).sum()) == 100 - 4
    assert not L.boundary_band(m, 0).any()
    assert not L.boundary_band(torch.zeros(5, 5, dtype=torch.bool), 2).any()  # no edge, no band
    assert not L.boundary_band(torch.ones(5, 5, dtype=torch.bool), 2).any()


def test_halo_target_is_the_low_pass_of_centres_on_the_silhouette():
    """Half-plane mask: 1 inside; outside, the mean over where the edge lies within the pixel gap of
    what a line of opaque centres on the edge renders through the Gaussian low-pass (checked by
    sampling the edge's sub-pixel position), 0.44 on the first ring at sigma 0.35, vanishing beyond."""
    sigma = 0.35
    m = torch.zeros(6, 8, dtype=torch.bool)
    m[:, :4] = True  # inside: columns 0-3; the first outside pixel centre is at x = 4.5
    t = L.halo_target(m, sigma)
    assert t.dtype == torch.float32 and t.shape == m.shape
    assert torch.equal(t[:, :4], torch.ones(6, 4))
    # the edge lies anywhere between the last inside centre (3.5) and the first outside one (4.5)
    edge = 3.5 + (np.arange(200000) + 0.5) / 200000
    for col in (4, 5, 6):
        d = (col + 0.5) - edge
        want = np.exp(-d ** 2 / (2 * sigma ** 2)).mean()
        np.testing.assert_allclose(t[:, col].numpy(), want, rtol=1e-4, atol=1e-7)
    assert abs(float(t[0, 4]) - 0.437) < 1e-3 and float(t[0, 5]) < 3e-3 and float(t[0, 7]) < 1e-12
    # a diagonal neighbour of the mask's corner is further away: a smaller target
    sq = torch.zeros(9, 9, dtype=torch.bool)
    sq[3:6, 3:6] = True
    ts = L.halo_target(sq, sigma)
    assert 0.05 < float(ts[2, 2]) < float(ts[2, 4]) < 0.5
    assert torch.equal(L.halo_target(torch.zeros(4, 4, dtype=torch.bool), sigma), torch.zeros(4, 4))
