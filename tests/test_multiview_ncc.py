# SPDX-License-Identifier: Apache-2.0
"""Multi-view window cost kernels (``kernels/multiview_ncc.py`` through :func:`wtopo.multiview_ncc.window_ncc_costs`):
the same costs, masks and gradients as the term's torch formulation they replace (pinhole and barrel lens,
the whole term's loss too), float64 finite differences, a fronto-parallel plane at its true depth scoring
NCC 1, and the stiff cases (grazing planes, untextured windows, windows leaving the source, depth 0 or
negative, a zero normal, repeated backward)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from lenses import barrel_twin
from reference.multiview import multiview_loss_torch, plane_costs_torch
from shapes import plane_truth, textured_plane

from wtopo.camera import Camera
from wtopo.fitting import multiview as M
from wtopo.multiview_ncc import ReferenceWindows, source_params, window_ncc_costs

# Kernel (float32) vs the torch formulation (float32): same operations in another order (sums of 49 window
# terms, shifted instead of centred moments, dot products instead of a matmul). Observed <= 1.5e-6 on the
# costs and <= 3e-5 of the largest gradient entry (pinhole and barrel); a 10x margin and more.
COST_ATOL = 2e-5
GRAD_REL = 5e-4
# the fronto-parallel plane: bilinear samples at pixel centres up to float32 round-off of the pixel
# coordinate (~1e-5 px at 64 px); observed <= 2e-6 off the exact cost
TRUE_PLANE_ATOL = 1e-4
HALF = 3
MIN_STD, GRAZING = M._MIN_STD, M._GRAZING


@pytest.fixture(scope="module")
def plane():
    return textured_plane()


def _off(d, n, a):
    """Maps off the truth in depth and tilt, so costs and gradients are not at a minimum (leaves)."""
    return ((d * 1.02).requires_grad_(True), (n + torch.tensor([0.2, -0.1, 0.0], device=n.device) * a[..., None])
            .requires_grad_(True))


def _centres(a, count, seed, h=HALF, unique=False):
    g = torch.Generator().manual_seed(seed)
    py, px = (a[h:-h, h:-h].cpu() > 0).nonzero(as_tuple=True)
    keep = torch.randperm(len(py), generator=g)[:count] if unique else torch.randint(len(py), (count,), generator=g)
    return (py[keep] + h).to(a.device), (px[keep] + h).to(a.device)


@pytest.mark.parametrize("lens", ["pinhole", "barrel"])
def test_costs_masks_and_gradients_match_the_torch_path(plane, device, lens):
    """Match the torch formulation the kernel replaced: costs, masks and the gradients of a random cotangent."""
    cams, imgs = (plane.cameras, plane.images) if lens == "pinhole" else barrel_twin(plane)
    mv = M.MultiViewNCC(cams, imgs, np.zeros(3), pixels=600, seed=0)
    d, n, a = plane_truth(cams[0], device)
    py, px = _centres(a, 600, 3)  # centres may repeat: the scatter adds them
    pick = mv._pick(0, 5)
    assert len(pick) == 2
    d1, n1 = _off(d, n, a)
    cost, ok = mv._plane_costs(0, py, px, d1, n1, a, pick)
    d2, n2 = _off(d, n, a)
    want, want_ok = plane_costs_torch(mv, 0, py, px, d2, n2, a, pick)
    assert torch.equal(ok > 0, want_ok)
    on = want_ok
    # windows that do not count are not scored (cost 2); the term weights them out
    assert float(on.float().mean()) > 0.3 and float(((want[on] > 0) & (want[on] < 2)).float().mean()) > 0.5
    torch.testing.assert_close(cost[on], want[on], atol=COST_ATOL, rtol=0)
    assert bool((cost[~on] == 2).all())
    w = torch.rand(len(py), generator=torch.Generator().manual_seed(4)).to(device) * on  # a random cotangent
    (cost * w).sum().backward()
    (want * w).sum().backward()
    for got, ref in ((d1.grad, d2.grad), (n1.grad, n2.grad)):
        assert float(ref.abs().max()) > 0, "the gradient was not exercised"
        err = float((got - ref).abs().max() / ref.abs().max())
        assert err < GRAD_REL, f"gradient off by {err:.3g} of its largest entry"


@pytest.mark.parametrize("it", [0, 7])
def test_term_matches_the_torch_path(plane, device, it):
    """Give the term's loss and map gradients of the torch formulation: same pixels, neighbours and masks."""
    mv = M.MultiViewNCC(plane.cameras, plane.images, np.zeros(3), pixels=4096, fraction=1 / 16, seed=2)
    for vi in (0, 3):
        d, n, a = plane_truth(plane.cameras[vi], device)
        d1, n1 = _off(d, n, a)
        d2, n2 = _off(d, n, a)
        got = mv(it, vi, d1, n1, a)
        want = multiview_loss_torch(mv, it, vi, d2, n2, a)
        torch.testing.assert_close(got, want, atol=COST_ATOL, rtol=0)
        got.backward()
        want.backward()
        for g, r in ((d1.grad, d2.grad), (n1.grad, n2.grad)):
            assert float(r.abs().max()) > 0
            assert float((g - r).abs().max() / r.abs().max()) < GRAD_REL


def _windows(gray: torch.Tensor, cam: Camera, h: int = HALF) -> ReferenceWindows:
    """The reference windows of a grey image as :class:`MultiViewNCC` makes them (float64 moments)."""
    g = gray.double()[None, None]
    k = 2 * h + 1
    mean = F.avg_pool2d(g, k, stride=1)
    var = (F.avg_pool2d(g * g, k, stride=1) - mean * mean).clamp_min(0.0)
    pad = (h, h, h, h)
    _, dirs = cam.pixel_rays("cpu", gray.dtype)
    return ReferenceWindows(gray, F.pad(mean, pad)[0, 0].to(gray.dtype), F.pad(var, pad)[0, 0].to(gray.dtype),
                            dirs, dirs.norm(dim=-1))


_SIZE, _FOCAL, _DEPTH, _SHIFT = 64, 60.0, 2.0, 4  # the source sees the plane z = 2 shifted by 4 pixels


def _stereo(dtype=torch.float32, texture="noise"):
    """A reference camera at the origin and a source moved sideways by ``SHIFT * DEPTH / FOCAL``: a plane at
    z = ``DEPTH`` appears in the source shifted left by ``SHIFT`` whole pixels, the source image is the
    reference image shifted so."""
    K = np.array([[_FOCAL, 0, _SIZE / 2], [0, _FOCAL, _SIZE / 2], [0, 0, 1]])
    ref = Camera(K, np.eye(4), _SIZE, _SIZE)
    w2c = np.eye(4)
    w2c[0, 3] = -_SHIFT * _DEPTH / _FOCAL
    src = Camera(K, w2c, _SIZE, _SIZE)
    g = torch.Generator().manual_seed(0)
    if texture == "noise":
        gray = F.avg_pool2d(torch.rand(1, 1, _SIZE, _SIZE + _SHIFT, generator=g, dtype=torch.float64), 3,
                            stride=1, padding=1)[0, 0]
    else:
        gray = torch.full((_SIZE, _SIZE + _SHIFT), 0.4, dtype=torch.float64)
    ref_img = gray[:, :_SIZE].to(dtype).contiguous()
    src_img = gray[:, _SHIFT:].to(dtype).contiguous()  # src[:, c] = ref[:, c + SHIFT]
    return ref, src, ref_img, src_img


def _maps(depth: float, normal=(0.0, 0.0, -1.0), dtype=torch.float32):
    d = torch.full((_SIZE, _SIZE), depth, dtype=dtype)
    n = torch.tensor(normal, dtype=dtype).expand(_SIZE, _SIZE, 3).contiguous()
    return d, n, torch.ones(_SIZE, _SIZE, dtype=dtype)


def _stereo_costs(d, n, a, py, px, texture="noise"):
    ref, src, ref_img, src_img = _stereo(d.dtype, texture)
    params = source_params(ref, src, dtype=d.dtype)[None]
    return window_ncc_costs(d, n, a, py, px, _windows(ref_img, ref), [src_img], params, half=HALF,
                            min_std=MIN_STD, grazing=GRAZING)


def _stereo_centres(count=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo = HALF + _SHIFT  # a window shifted left by SHIFT stays inside the source
    return (torch.randint(HALF, _SIZE - HALF, (count,), generator=g),
            torch.randint(lo, _SIZE - HALF, (count,), generator=g))


def test_fronto_parallel_plane_at_its_depth_scores_ncc_one():
    """Score NCC 1 on the true fronto-parallel plane (cost 0 but for ``eps``); 15 % off the depth scores
    worse and its gradient points back."""
    py, px = _stereo_centres()
    cost, ok = _stereo_costs(*_maps(_DEPTH), py, px)
    assert bool((ok > 0).all())
    # the source window is the reference window: NCC = var / sqrt(var^2 + eps), eps = 1e-6
    ref, _, ref_img, _ = _stereo()
    var = _windows(ref_img, ref).var[py, px]
    torch.testing.assert_close(cost, 1.0 - var / (var * var + 1e-6).sqrt(), atol=TRUE_PLANE_ATOL, rtol=0)
    assert float(cost.max()) < 0.1
    true = float(cost.mean())
    for scale, sign in ((1.15, 1.0), (0.87, -1.0)):  # about 0.6 px of shift in the source
        d, n, a = _maps(_DEPTH * scale)
        d.requires_grad_(True)
        cost, ok = _stereo_costs(d, n, a, py, px)
        assert float(cost.mean()) > 3 * true, f"{float(cost.mean()):.3g} at {scale}, {true:.3g} at the truth"
        cost.sum().backward()
        assert sign * float(d.grad.sum()) > 0, f"d cost / d depth = {float(d.grad.sum()):.3g} at {scale}"


def test_gradients_match_finite_differences_in_float64():
    """Pass ``torch.autograd.gradcheck`` in float64 w.r.t. the windows' depths and normals (scattered into maps)."""
    dt = torch.float64
    ref, src, ref_img, src_img = _stereo(dt)
    win = _windows(ref_img, ref)
    params = source_params(ref, src, dtype=dt)
    py, px = _stereo_centres(6, seed=1)
    flat = torch.unique(py * _SIZE + px)  # distinct centres: each input entry is one window's
    py, px = flat // _SIZE, flat % _SIZE
    base_d, base_n, a = _maps(_DEPTH, dtype=dt)
    # two sources (the second the first with a brighter copy of the image), each window against both
    images, rows = [src_img, 0.5 * src_img + 0.2], torch.stack([params, params])

    def f(dv, nv):
        d = base_d.index_put((py, px), dv)
        n = base_n.index_put((py, px), nv)
        return window_ncc_costs(d, n, a, py, px, win, images, rows, half=HALF, min_std=MIN_STD,
                                grazing=GRAZING)[0]

    g = torch.Generator().manual_seed(5)
    dv = (_DEPTH * (1.03 + 0.02 * torch.rand(len(py), generator=g, dtype=dt))).requires_grad_(True)
    nv = (torch.tensor([0.1, -0.2, -1.0], dtype=dt) + 0.05 * torch.randn(len(py), 3, generator=g, dtype=dt))
    nv.requires_grad_(True)
    cost = f(dv, nv)
    assert bool(((cost > 0) & (cost < 2)).all()), "every window must be scored (not clamped)"
    assert torch.autograd.gradcheck(f, (dv, nv), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_grazing_planes_untextured_windows_and_bad_depths_do_not_count():
    """Leave out grazing planes, untextured windows and depth 0 or negative (``ok`` 0, cost 2), with finite
    gradients; a window sent outside the source costs 2; none of them passes a gradient."""
    py, px = _stereo_centres(50)
    # at every pixel a plane containing its ray (a normal across it): every window grazes
    d, n, a = _maps(_DEPTH)
    x = (torch.arange(_SIZE) + 0.5 - _SIZE / 2) / _FOCAL  # the rays' camera x over z
    n = torch.stack([torch.ones(_SIZE), torch.zeros(_SIZE), -x], -1).expand(_SIZE, _SIZE, 3).contiguous()
    d.requires_grad_(True)
    n.requires_grad_(True)
    cost, ok = _stereo_costs(d, n, a, py, px)
    assert not bool(ok.any()) and bool((cost == 2).all())
    cost.sum().backward()
    assert float(d.grad.abs().sum()) == 0.0 and float(n.grad.abs().sum()) == 0.0
    # flat grey photographs: no texture
    cost, ok = _stereo_costs(*_maps(_DEPTH), py, px, texture="flat")
    assert not bool(ok.any()) and bool((cost == 2).all())
    for depth in (0.0, -1.0, 1e-3):  # at the centre, behind it, a plane so near the window leaves the source
        d, n, a = _maps(depth)
        d.requires_grad_(True)
        n.requires_grad_(True)
        cost, ok = _stereo_costs(d, n, a, py, px)
        assert bool((ok > 0).all()) == (depth > 0)
        assert bool((cost == 2.0).all()), f"depth {depth}: costs {cost.unique()}"
        cost.sum().backward()
        assert float(d.grad.abs().sum()) == 0.0 and float(n.grad.abs().sum()) == 0.0


def test_zero_normal_is_finite_and_does_not_count():
    """Treat a zero rendered normal (nothing rendered) as a grazing plane: finite, ``ok`` 0."""
    py, px = _stereo_centres(20)
    d, n, a = _maps(_DEPTH, normal=(0.0, 0.0, 0.0))
    n.requires_grad_(True)
    cost, ok = _stereo_costs(d, n, a, py, px)
    assert not bool(ok.any()) and bool(torch.isfinite(cost).all())
    cost.sum().backward()
    assert bool(torch.isfinite(n.grad).all())


def test_repeated_backward_gives_the_same_gradient():
    """Differentiate the same graph twice (``retain_graph``): the same gradient, not twice it."""
    py, px = _stereo_centres(40)
    d, n, a = _maps(_DEPTH * 1.04)
    d.requires_grad_(True)
    cost, _ = _stereo_costs(d, n, a, py, px)
    first = torch.autograd.grad(cost.sum(), d, retain_graph=True)[0]
    second = torch.autograd.grad(cost.sum(), d)[0]
    assert float(first.abs().sum()) > 0
    torch.testing.assert_close(first, second, atol=0, rtol=0)


def test_bad_arguments_are_named():
    """Raise naming the argument: dtype, shapes, source count, window size, centres too near the border."""
    ref, src, ref_img, src_img = _stereo()
    win = _windows(ref_img, ref)
    params = source_params(ref, src)[None]
    d, n, a = _maps(_DEPTH)
    py, px = _stereo_centres(4)

    def call(**kw):
        args = dict(depth=d, normal=n, alpha=a, py=py, px=px, reference=win, images=[src_img], params=params)
        args.update(kw)
        half = args.pop("half", HALF)
        return window_ncc_costs(*args.values(), half=half, min_std=MIN_STD, grazing=GRAZING)

    with pytest.raises(TypeError, match="normal"):
        call(normal=n.double())
    with pytest.raises(ValueError, match="alpha"):
        call(alpha=a[1:])
    with pytest.raises(TypeError, match="py"):
        call(py=py.int())
    with pytest.raises(ValueError, match="images"):
        call(images=[src_img] * 3, params=params.expand(3, -1))
    with pytest.raises(ValueError, match="params"):
        call(params=params[:, :5])
    with pytest.raises(ValueError, match="half"):
        call(half=40)
    with pytest.raises(ValueError, match="inside"):
        call(px=torch.zeros_like(px))
