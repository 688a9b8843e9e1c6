# SPDX-License-Identifier: Apache-2.0
"""The fused per-pixel normal, distortion and mask terms (``kernels/pixel_terms.py`` through
:func:`wtopo.pixel_terms.pixel_terms`): equal to the torch formulation they replaced, values and gradients
(float32 and float64, one launch and a launch split across CPU threads, every device); float64 finite
differences; a plane's exact terms; no pixel with a depth normal, opacities at 0 and 1, zero normals and empty
or tiny images stay finite; and the argument errors name the argument."""

from __future__ import annotations

import math

import pytest
import torch
from reference.pixel_terms import pixel_terms_torch

from wtopo.pixel_terms import pixel_terms

# float32: the fused pass sums runs of 64 pixels and then the runs, torch sums in its own blocks; observed
# <= 2e-7 relative on the terms and <= 3e-8 absolute on gradients of size ~1e-4..2 (the mask's 1 / a at
# small opacities); margins of 10x and more
RTOL = {torch.float32: 5e-6, torch.float64: 1e-12}
GRAD_ATOL = {torch.float32: 1e-6, torch.float64: 1e-14}


def _rays(h, w, dtype, device, f=40.0):
    j, i = torch.meshgrid(torch.arange(w, dtype=dtype) + 0.5, torch.arange(h, dtype=dtype) + 0.5, indexing="xy")
    d = torch.stack([(j - w / 2) / f, (i - h / 2) / f, torch.ones_like(j)], -1)
    o = torch.tensor([0.1, -0.2, 0.3], dtype=dtype).expand(h, w, 3).contiguous()
    return o.to(device), d.to(device)


def _maps(h, w, dtype, device, seed=0):
    """Rough rendered maps: a bumpy depth with a step, opacities in (0.02, 0.98), random normals and distortion,
    a random boolean mask; ``valid`` the opacity >= 0.5, as the fit's."""
    g = torch.Generator().manual_seed(seed)
    depth = 2.0 + 0.05 * torch.rand(h, w, generator=g, dtype=dtype)
    depth[:, w // 2:] += 1.0
    alpha = 0.02 + 0.96 * torch.rand(h, w, generator=g, dtype=dtype)
    normal = torch.randn(h, w, 3, generator=g, dtype=dtype) * alpha[..., None]
    dist = torch.rand(h, w, generator=g, dtype=dtype) * 1e-3
    target = torch.rand(h, w, generator=g) > 0.5
    maps = [t.to(device) for t in (normal, alpha, depth, dist)]
    for t in (maps[0], maps[1], maps[3]):
        t.requires_grad_()
    return (*maps, maps[1].detach() >= 0.5, target.to(device))


def _loss(terms):
    return 0.05 * terms[0] + 100.0 * terms[1] + 0.7 * terms[2]


@pytest.mark.parametrize("hw", [(23, 37), (260, 520)])  # one CPU launch; a launch split across threads
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_equals_the_torch_formulation(device, dtype, hw):
    """The three terms and their gradients w.r.t. the normal, opacity and distortion equal the reference's."""
    h, w = hw
    normal, alpha, depth, dist, valid, target = _maps(h, w, dtype, device)
    o, d = _rays(h, w, dtype, device)
    ours = pixel_terms(normal, alpha, depth, dist, o, d, valid, target)
    ref = pixel_terms_torch(normal, alpha, depth, dist, o, d, valid, target)
    for a, b in zip(ours, ref):
        assert a.dtype == dtype and a.shape == () and a.device == alpha.device
        torch.testing.assert_close(a, b, rtol=RTOL[dtype], atol=0)
    assert float(ours.normal.detach()) > 0.0 and int(valid.sum()) > 50
    g_ours = torch.autograd.grad(_loss(ours), (normal, alpha, dist))
    g_ref = torch.autograd.grad(_loss(ref), (normal, alpha, dist))
    for a, b in zip(g_ours, g_ref):
        torch.testing.assert_close(a, b, atol=GRAD_ATOL[dtype], rtol=0)
    # no mask: the same normal and distortion terms, no mask term and no opacity gradient
    plain = pixel_terms(normal, alpha, depth, dist, o, d, valid)
    assert plain.mask is None
    torch.testing.assert_close(plain.normal, ours.normal, rtol=0, atol=0)
    (ga,) = torch.autograd.grad(plain.normal + plain.distortion, (alpha,), allow_unused=True)
    assert ga is None or not ga.any()


def test_the_cuda_run_length_gives_the_same_terms_on_the_cpu(monkeypatch):
    """The forward's runs of 16 pixels (CUDA's; a row of 37 ends in a run of 5) sum the same terms as runs of
    64, and their gradients reach each pixel from its own run."""
    import wtopo.pixel_terms as P

    normal, alpha, depth, dist, valid, target = _maps(23, 37, torch.float64, "cpu")
    o, d = _rays(23, 37, torch.float64, "cpu")
    ref = pixel_terms_torch(normal, alpha, depth, dist, o, d, valid, target)
    monkeypatch.setattr(P, "_RUN_CPU", P._RUN_CUDA)
    ours = pixel_terms(normal, alpha, depth, dist, o, d, valid, target)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=RTOL[torch.float64], atol=0)
    for a, b in zip(torch.autograd.grad(_loss(ours), (normal, alpha, dist)),
                    torch.autograd.grad(_loss(ref), (normal, alpha, dist))):
        torch.testing.assert_close(a, b, atol=GRAD_ATOL[torch.float64], rtol=0)


def test_float64_finite_differences(device):
    """torch.autograd.gradcheck of each term w.r.t. what it differentiates (two runs per row): the normal term
    w.r.t. the rendered normal (the opacity in it is held fixed, as in 2DGS), the distortion term w.r.t. the
    distortion map, the mask term w.r.t. the opacity."""
    normal, alpha, depth, dist, valid, target = _maps(9, 70, torch.float64, device, seed=3)
    o, d = _rays(9, 70, torch.float64, device)
    a0, n0, d0 = alpha.detach(), normal.detach(), dist.detach()
    checks = ((lambda n: pixel_terms(n, a0, depth, d0, o, d, valid, target).normal, normal),
              (lambda di: pixel_terms(n0, a0, depth, di, o, d, valid, target).distortion, dist),
              (lambda a: pixel_terms(n0, a, depth, d0, o, d, valid, target).mask, alpha))
    for f, x in checks:
        assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_a_plane_rendered_exactly_scores_its_known_terms(device):
    """A plane z = 2 seen from the origin, rendered with opacity 0.8 and normal 0.8 (0, 0, -1): normal term 0 over
    the inner pixels; a constant distortion 0.25 is its own mean; opacity 0.5 against any mask is log 2, with
    gradient -(1 / 0.5) / (H W) where the mask is 1 and +(1 / 0.5) / (H W) where it is 0."""
    h, w = 12, 20
    dt = torch.float64
    o, d = _rays(h, w, dt, device)
    o = torch.zeros_like(o)
    depth = torch.full((h, w), 2.0, dtype=dt, device=device)
    normal = (0.8 * torch.tensor([0.0, 0.0, -1.0], dtype=dt, device=device)).expand(h, w, 3).clone().requires_grad_()
    alpha = torch.full((h, w), 0.8, dtype=dt, device=device)
    dist = torch.full((h, w), 0.25, dtype=dt, device=device)
    valid = torch.ones(h, w, dtype=torch.bool, device=device)
    t = pixel_terms(normal, alpha, depth, dist, o, d, valid)
    assert abs(float(t.normal.detach())) < 1e-14 and float(t.distortion.detach()) == pytest.approx(0.25, abs=1e-15)
    (gn,) = torch.autograd.grad(t.normal, normal)
    inner = (h - 2) * (w - 2)
    want = torch.zeros(h, w, 3, dtype=dt, device=device)
    want[1:-1, 1:-1, 2] = 1.0 / inner  # -(n_depth) / count, n_depth = (0, 0, -1)
    torch.testing.assert_close(gn, want, atol=1e-15, rtol=0)
    half = torch.full((h, w), 0.5, dtype=dt, device=device, requires_grad=True)
    target = torch.zeros(h, w, dtype=torch.bool, device=device)
    target[:, : w // 2] = True
    m = pixel_terms(normal, half, depth, dist, o, d, valid, target).mask
    assert float(m.detach()) == pytest.approx(math.log(2.0), abs=1e-14)
    (ga,) = torch.autograd.grad(m, half)
    assert torch.allclose(ga[:, : w // 2], torch.tensor(-2.0 / (h * w), dtype=dt, device=device), atol=1e-15)
    assert torch.allclose(ga[:, w // 2:], torch.tensor(2.0 / (h * w), dtype=dt, device=device), atol=1e-15)


def test_degenerate_inputs_stay_finite(device):
    """No pixel with a depth normal (nothing valid, or a view too small for central differences) gives a normal
    term of exactly 0 with zero gradients; opacities of exactly 0 and 1 against the mask are clamped (finite
    term, zero gradient there); zero rendered normals are fine; an empty view gives zeros on the graph."""
    dt = torch.float32
    normal, alpha, depth, dist, valid, target = _maps(16, 16, dt, device)
    o, d = _rays(16, 16, dt, device)
    none = torch.zeros_like(valid)
    t = pixel_terms(normal, alpha, depth, dist, o, d, none, target)
    assert float(t.normal.detach()) == 0.0
    (gn,) = torch.autograd.grad(t.normal, normal)
    assert torch.isfinite(gn).all() and not gn.any()
    tiny = pixel_terms(*(x[:2, :5] for x in (normal, alpha, depth, dist, o, d, valid, target)))
    assert float(tiny.normal.detach()) == 0.0 and all(torch.isfinite(x) for x in tiny)
    hard = alpha.detach().clone()
    hard[:4] = 0.0
    hard[4:8] = 1.0
    hard.requires_grad_()
    zero_n = torch.zeros_like(normal, requires_grad=True)
    t = pixel_terms(zero_n, hard, depth, dist, o, d, hard.detach() >= 0.5, target)
    assert all(torch.isfinite(x) for x in t)
    g = torch.autograd.grad(t.normal + t.mask, (zero_n, hard))
    assert all(torch.isfinite(x).all() for x in g) and not g[1][:8].any() and g[1][8:].any()
    e = torch.zeros(0, 0, dtype=dt, device=device, requires_grad=True)
    e3 = torch.zeros(0, 0, 3, dtype=dt, device=device)
    empty = pixel_terms(e3, e, e.detach(), e, e3, e3, torch.zeros(0, 0, dtype=torch.bool, device=device),
                        torch.zeros(0, 0, dtype=torch.bool, device=device))
    assert all(float(x.detach()) == 0.0 for x in empty) and empty.mask.requires_grad


def test_bad_arguments_are_named():
    """Wrong shapes, dtypes, a non-finite map and bad constants raise naming the argument and the value."""
    normal, alpha, depth, dist, valid, target = _maps(8, 8, torch.float32, "cpu")
    o, d = _rays(8, 8, torch.float32, "cpu")
    with pytest.raises(ValueError, match="normal must have shape"):
        pixel_terms(normal[:, :4], alpha, depth, dist, o, d, valid)
    with pytest.raises(TypeError, match="distortion must have dtype"):
        pixel_terms(normal, alpha, depth, dist.double(), o, d, valid)
    with pytest.raises(TypeError, match="valid must have dtype"):
        pixel_terms(normal, alpha, depth, dist, o, d, valid.float())
    with pytest.raises(ValueError, match="target must have shape"):
        pixel_terms(normal, alpha, depth, dist, o, d, valid, target[:3])
    bad = depth.clone()
    bad[2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"median_depth must be finite, got nan at index \[2, 3\]"):
        pixel_terms(normal, alpha, bad, dist, o, d, valid)
    with pytest.raises(ValueError, match="clamp must be a number in"):
        pixel_terms(normal, alpha, depth, dist, o, d, valid, clamp=0.5)
    with pytest.raises(ValueError, match="eps"):
        pixel_terms(normal, alpha, depth, dist, o, d, valid, eps=-1.0)
