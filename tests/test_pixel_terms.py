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
    """The terms as the objective wrote them before they were one function (the multi-view term by its class)."""
    out = [photometric(render.rgb, image, ts.dssim)]
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
