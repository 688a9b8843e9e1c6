# SPDX-License-Identifier: Apache-2.0
"""The per-pixel loss terms (``wtopo.fitting.pixel_terms``): the terms of the losses module and the multi-view term,
eager or replayed as CUDA graphs, with the same values and gradients; a set whose capture fails runs eagerly."""

from __future__ import annotations

import functools
import itertools
import types

import numpy as np
import pytest
import torch
from shapes import plane_truth, textured_plane

from wtopo.depth_normals import depth_normals
from wtopo.fitting import pixel_terms as P
from wtopo.fitting.losses import distortion, mask_loss, normal_consistency, photometric
from wtopo.fitting.multiview import MultiViewNCC


@functools.cache
def _plane():
    """The textured quad's scene (96 x 72 px, 8 views) and its multi-view term."""
    sc = textured_plane()
    return sc, MultiViewNCC(sc.cameras, sc.images, np.zeros(3), pixels=400, seed=0)


def _view(device, seed: int, vi: int = 0):
    """A rendering of view ``vi`` of the quad near the truth (depth 2 % off, noisy normals, colours and opacity),
    its photograph, a mask, its rays and the multi-view term's windows at iteration ``seed``."""
    sc, mv = _plane()
    cam = sc.cameras[vi]
    H, W = cam.height, cam.width
    g = torch.Generator().manual_seed(seed)

    def t(*shape, lo=0.0, hi=1.0):
        return (torch.rand(*shape, generator=g) * (hi - lo) + lo).to(device)

    d, n, a = (x.to(device) for x in plane_truth(cam))
    image = torch.as_tensor(sc.images[vi]).float().to(device)
    render = types.SimpleNamespace(
        rgb=(image * 0.8 + t(H, W, 3, hi=0.2)).requires_grad_(),
        alpha=(a * 0.85 + t(H, W, lo=0.05, hi=0.1)).requires_grad_(),
        normal=torch.nn.functional.normalize(n + t(H, W, 3, lo=-0.2, hi=0.2), dim=-1).requires_grad_(),
        distortion=t(H, W, hi=0.01).requires_grad_(), median_depth=(d * 1.02).requires_grad_())
    return render, image, t(H, W) > 0.3, cam.pixel_rays(device), mv.draw(seed, vi, torch.device(device))


def _direct(ts, render, image, mask, rays, windows, seed: int = 0, vi: int = 0):
    """The terms as the objective wrote them before they were one function (the multi-view term by its class), the
    photometric term on the photograph's colour in the mask's halo ring."""
    rgb = render.rgb if mask is None else torch.where(P.halo_ring(mask)[..., None], image, render.rgb)
    out = [photometric(rgb, image, ts.dssim)]
    if ts.mask:
        out.append(ts.mask * mask_loss(render.alpha, mask.to(render.alpha.dtype)))
    if ts.normal:
        covered = render.alpha.detach() >= P.ALPHA_COVERED
        dn, dmask = depth_normals(render.median_depth.detach(), *rays, covered)
        out.append(ts.normal * normal_consistency(render.normal, dn, render.alpha, dmask))
    if ts.distortion:
        out.append(ts.distortion * distortion(render.distortion))
    if ts.multiview:
        out.append(ts.multiview * _plane()[1](seed, vi, render.median_depth, render.normal, render.alpha))
    return torch.stack(out)


def _grads(values, render):
    leaves = (render.rgb, render.alpha, render.normal, render.distortion, render.median_depth)
    gs = torch.autograd.grad(values.sum(), leaves, allow_unused=True)
    return [torch.zeros_like(x) if g is None else g for g, x in zip(gs, leaves)]


def _mv(weight: float) -> dict:
    return {"multiview": weight, "sources": 2, "half": 3} if weight else {}


SETS = [P.TermSet(0.2, mask=m, normal=n, distortion=d, **_mv(v))
        for m, n, d, v in itertools.product((0.0, 0.5), (0.0, 0.05), (0.0, 100.0), (0.0, 0.2))]


@pytest.mark.parametrize("ts", SETS, ids=lambda ts: "+".join(ts.names))
def test_terms_equal_the_losses_modules_terms_with_their_gradients(device, ts, monkeypatch):
    """Eagerly, every set of terms gives the losses module's values, in :attr:`TermSet.names`' order, and the same
    gradients w.r.t. every rendered image."""
    monkeypatch.setattr(P, "GRAPHS", False)
    render, image, mask, rays, windows = _view(device, 0)
    got = P.PixelTerms()(ts, render, image, mask, rays, windows)
    want = _direct(ts, render, image, mask, rays, windows)
    assert got.shape == (len(ts.names),)
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    for a, b in zip(_grads(got, render), _grads(want, render)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
@pytest.mark.parametrize("ts", [SETS[0], SETS[-2], SETS[-1], P.TermSet(0.2, normal=0.05),
                                P.TermSet(0.2, normal=0.05, **_mv(0.2))], ids=lambda ts: "+".join(ts.names))
def test_graphed_terms_replay_the_eager_ones_on_new_views(ts):
    """On CUDA the terms are captured once per set and size and replayed: over views the capture never saw,
    values and gradients equal the eager terms', and a second set gets its own graph."""
    from conftest import CUDA_DEVICE

    terms = P.PixelTerms()
    for seed in range(3):
        render, image, mask, rays, windows = _view(CUDA_DEVICE, seed, vi=seed)
        got = terms(ts, render, image, mask, rays, windows)
        want = _direct(ts, render, image, mask, rays, windows, seed, vi=seed)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=0)
        for a, b in zip(_grads(got, render), _grads(want, render)):
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)
    assert len(terms._graphs) == 1 and not terms.failures  # noqa: SLF001


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_a_failed_capture_leaves_the_set_eager_and_says_why(monkeypatch):
    """A capture that raises leaves its set eager for good, with a warning and the reason in ``failures``."""
    from conftest import CUDA_DEVICE

    def broken(*a, **k):
        raise RuntimeError("no graphs here")

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", broken)
    terms = P.PixelTerms()
    ts = SETS[-1]
    render, image, mask, rays, windows = _view(CUDA_DEVICE, 0)
    with pytest.warns(RuntimeWarning, match="no graphs here"):
        got = terms(ts, render, image, mask, rays, windows)
    torch.testing.assert_close(got, _direct(ts, render, image, mask, rays, windows), rtol=0, atol=0)
    assert list(terms.failures.values()) == ["RuntimeError: no graphs here"]
    render, image, mask, rays, windows = _view(CUDA_DEVICE, 1)
    torch.testing.assert_close(terms(ts, render, image, mask, rays, windows),
                               _direct(ts, render, image, mask, rays, windows, 1))


@pytest.mark.parametrize("ts", SETS, ids=lambda ts: "+".join(ts.names))
def test_every_differentiable_input_of_a_set_gets_a_gradient(ts):
    """What a graph's capture needs (``torch.cuda.make_graphed_callables`` differentiates every input that requires
    a gradient and fails on one the terms do not use, as on the H200 for the normal term without the mask's): each
    set's inputs require gradients exactly where its terms differentiate them."""
    render, image, mask, rays, windows = _view("cpu", 0)
    args = P._inputs(ts, render, image, mask, rays, windows)  # noqa: SLF001
    diff = [a for a in args if a.requires_grad]
    grads = torch.autograd.grad(P._terms_fn(ts)(*args).sum(), diff, allow_unused=False)  # noqa: SLF001
    assert all(g is not None and torch.count_nonzero(g) > 0 for g in grads)


def test_the_multiview_term_needs_its_windows():
    render, image, mask, rays, windows = _view("cpu", 0)
    ts = P.TermSet(0.2, **_mv(0.2))
    with pytest.raises(ValueError, match="2 images and half side 3, got None"):
        P.PixelTerms()(ts, render, image, mask, rays, None)
    with pytest.raises(ValueError, match=r"got \(1, 3\)"):
        P.PixelTerms()(ts, render, image, mask, rays, windows._replace(images=windows.images[:1]))


def test_the_halo_ring_is_the_border_just_outside_the_mask():
    """Analytic: a 3 x 3 square's ring of width 1 is the 5 x 5 square around it less the square (16 pixels), of width
    2 the 7 x 7 one less it (40); a float mask is inside from 0.5; the ring stops at the image's edge."""
    m = torch.zeros(10, 12, dtype=torch.bool)
    m[3:6, 4:7] = True
    want = torch.zeros_like(m)
    want[2:7, 3:8] = True
    want &= ~m
    assert torch.equal(P.halo_ring(m), want) and int(P.halo_ring(m).sum()) == 16
    assert int(P.halo_ring(m, 2).sum()) == 40 and not (P.halo_ring(m, 2) & m).any()
    soft = m.float() * 0.6 + 0.3 * (~m).float()  # 0.6 inside, 0.3 outside
    assert torch.equal(P.halo_ring(soft), want)
    corner = torch.zeros(4, 4, dtype=torch.bool)
    corner[0, 0] = True
    assert P.halo_ring(corner).nonzero().tolist() == [[0, 1], [1, 0], [1, 1]]
    assert not P.halo_ring(torch.ones(5, 5, dtype=torch.bool)).any()
    stacked = torch.stack([m, m.flip(0), torch.zeros_like(m)])  # views' masks at once: each view's own ring
    assert torch.equal(P.halo_ring(stacked), torch.stack([P.halo_ring(x) for x in stacked]))
    with pytest.raises(ValueError, match="width must be at least 1 pixel, got 0"):
        P.halo_ring(m, 0)


@pytest.mark.parametrize("dssim", [0.0, 0.2])
def test_a_halo_just_outside_the_mask_costs_the_photometric_term_nothing(device, dssim, monkeypatch):
    """A render equal to the photograph inside the mask, with a bright halo in the one-pixel ring outside it (what
    surfels on the true surface render at its limb), scores 0 with the mask (L1 and SSIM alike) and has no gradient
    there; the same halo one pixel farther out, or without the mask, costs and pulls."""
    monkeypatch.setattr(P, "GRAPHS", False)
    g = torch.Generator().manual_seed(0)
    H, W = 24, 20
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[6:18, 5:15] = True
    image = torch.where(mask[..., None], torch.rand(H, W, 3, generator=g) * 0.8 + 0.1, torch.zeros(H, W, 3))
    ring = P.halo_ring(mask)
    far = P.halo_ring(mask, 2) & ~ring
    ts = P.TermSet(dssim)

    def cost(halo):
        rgb = torch.where(halo[..., None], torch.full((H, W, 3), 0.7), image).to(device).requires_grad_()
        render = types.SimpleNamespace(rgb=rgb)
        value = P.PixelTerms()(ts, render, image.to(device), mask.to(device), None)[0]
        value.backward()
        return float(value.detach()), rgb.grad.abs().sum(-1).cpu()

    value, grad = cost(ring)
    assert value == 0.0 and torch.count_nonzero(grad[ring]) == 0
    rgb = torch.where(ring[..., None], torch.full((H, W, 3), 0.7), image).to(device)
    kept = P.PixelTerms()(ts, types.SimpleNamespace(rgb=rgb), image.to(device), mask.to(device), None,
                          ring=ring.to(device))[0]  # the caller's ring in place of the mask's
    assert float(kept) == 0.0
    value, grad = cost(far)
    assert value > 1e-3 and torch.count_nonzero(grad[far]) == int(far.sum())
    rgb = torch.where(ring[..., None], torch.full((H, W, 3), 0.7), image).to(device)
    assert float(P.PixelTerms()(ts, types.SimpleNamespace(rgb=rgb), image.to(device), None, None)[0]) > 1e-3
