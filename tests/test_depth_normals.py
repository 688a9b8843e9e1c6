# SPDX-License-Identifier: Apache-2.0
"""Depth-map normals (``kernels/depth_normals.py`` through :func:`wtopo.depth_normals.depth_normals`): equal to
the torch formulation it replaced on a rough surface with holes and jumps (float32 and float64, every device),
a tilted plane's exact normal, the masks at borders, invalid neighbours, zero-length and non-finite cases,
tiny images, and the argument errors."""

from __future__ import annotations

import math

import pytest
import torch
from reference.depth_normals import depth_normals_torch

from wtopo.depth_normals import depth_normals

# the kernel and the reference compute the same expressions in the same order but for the norm (one
# sqrt of a sum of three squares either way) and torch's fused ops: observed <= 2.4e-7 in float32
ATOL = {torch.float32: 2e-6, torch.float64: 1e-12}


def _rays(h, w, f=50.0, dtype=torch.float32, device="cpu"):
    """Pinhole rays from (0.1, -0.2, 0.3) looking down +z, camera-z component 1."""
    j, i = torch.meshgrid(torch.arange(w, dtype=dtype) + 0.5, torch.arange(h, dtype=dtype) + 0.5, indexing="xy")
    d = torch.stack([(j - w / 2) / f, (i - h / 2) / f, torch.ones_like(j)], -1)
    o = torch.tensor([0.1, -0.2, 0.3], dtype=dtype).expand(h, w, 3).contiguous()
    return o.to(device), d.to(device)


def _rough(h, w, dtype, device, seed=0):
    """A bumpy surface with a step, holes in ``valid`` and a few pixels at depth 0."""
    g = torch.Generator().manual_seed(seed)
    depth = 2.0 + 0.05 * torch.rand(h, w, generator=g, dtype=dtype)
    depth[:, w // 2:] += 1.5
    depth[3, 4] = 0.0
    valid = (torch.rand(h, w, generator=g) > 0.15) & (depth > 0)
    return depth.to(device), valid.to(device)


@pytest.mark.parametrize("hw", [(23, 37), (130, 70)])  # one CPU launch; a launch split across threads
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_equals_the_torch_formulation(device, dtype, hw):
    """Normals and mask equal the reference's on a rough surface with holes, a step and zero depths."""
    h, w = hw
    o, d = _rays(h, w, dtype=dtype, device=device)
    depth, valid = _rough(h, w, dtype, device)
    n, m = depth_normals(depth, o, d, valid)
    rn, rm = depth_normals_torch(depth, o, d, valid)
    assert n.dtype == dtype and n.shape == (h, w, 3) and m.dtype == torch.bool and m.device == depth.device
    assert torch.equal(m, rm) and 50 < int(m.sum()) < (h - 2) * (w - 2)
    torch.testing.assert_close(n, rn, atol=ATOL[dtype], rtol=0)


def test_tilted_plane_has_its_exact_normal_facing_the_camera(device):
    """A plane z = 2 + 0.3 x seen from the origin: every inner pixel has (0.3, 0, -1) / |.|, borders zero."""
    h = w = 16
    o, d = _rays(h, w, dtype=torch.float64, device=device)
    o = torch.zeros_like(o)
    depth = 2.0 / (1 - 0.3 * d[..., 0])  # ray x = d_x t, z = t
    n, m = depth_normals(depth, o, d, torch.ones(h, w, dtype=torch.bool, device=device))
    want = torch.tensor([0.3, 0.0, -1.0], dtype=torch.float64, device=device) / math.sqrt(1.09)
    assert m[1:-1, 1:-1].all() and not m[0].any() and not m[-1].any() and not m[:, 0].any() and not m[:, -1].any()
    torch.testing.assert_close(n[1:-1, 1:-1], want.expand(h - 2, w - 2, 3), atol=1e-12, rtol=0)
    assert torch.equal(n[0], torch.zeros(w, 3, dtype=torch.float64, device=device))
    # the same plane seen from behind: the normal still faces the rays
    n2, _ = depth_normals(depth, o, -d, torch.ones(h, w, dtype=torch.bool, device=device))
    assert ((n2[1:-1, 1:-1] * -d[1:-1, 1:-1]).sum(-1) < 0).all()


def test_invalid_neighbours_and_degenerate_pixels_are_masked(device):
    """An invalid pixel masks itself and its four neighbours; a zero-length cross product (all depths 0 at the
    origin) gives a zero normal and no mask; outputs stay finite."""
    h, w = 8, 9
    o, d = _rays(h, w, device=device)
    depth = torch.ones(h, w, device=device)
    valid = torch.ones(h, w, dtype=torch.bool, device=device)
    valid[4, 4] = False
    n, m = depth_normals(depth, o, d, valid)
    for y, x in ((4, 4), (3, 4), (5, 4), (4, 3), (4, 5)):
        assert not m[y, x] and not n[y, x].any()
    assert m[2, 2] and m[6, 6]
    n0, m0 = depth_normals(torch.zeros(h, w, device=device), torch.zeros_like(o), d, valid)
    assert not m0.any() and not n0.any()
    # eps above every cross product: nothing has a normal
    n1, m1 = depth_normals(depth, o, d, valid, eps=1e3)
    assert not m1.any() and torch.isfinite(n1).all()


@pytest.mark.parametrize("hw", [(1, 1), (2, 7), (3, 3), (0, 4)])
def test_tiny_and_empty_images(device, hw):
    """Images with no inner pixel (or none at all) give zero normals and an empty mask, no launch error."""
    h, w = hw
    o, d = _rays(h, w, device=device)
    n, m = depth_normals(torch.ones(h, w, device=device), o, d, torch.ones(h, w, dtype=torch.bool, device=device))
    assert n.shape == (h, w, 3) and m.shape == (h, w)
    if h == 3 and w == 3:
        assert m.sum() == 1 and m[1, 1]
    else:
        assert not m.any() and not n.any()


def test_outputs_are_detached():
    """The normals carry no graph even from a depth that requires a gradient (the fit's fixed target)."""
    o, d = _rays(6, 6)
    depth = torch.ones(6, 6, requires_grad=True)
    n, m = depth_normals(depth, o, d, torch.ones(6, 6, dtype=torch.bool))
    assert not n.requires_grad and n.grad_fn is None


def test_bad_arguments_raise_before_any_launch():
    o, d = _rays(5, 6)
    depth, valid = torch.ones(5, 6), torch.ones(5, 6, dtype=torch.bool)
    with pytest.raises(ValueError, match="origins must have shape"):
        depth_normals(depth, o[:4], d, valid)
    with pytest.raises(TypeError, match="directions must have dtype"):
        depth_normals(depth, o, d.double(), valid)
    with pytest.raises(TypeError, match="valid must have dtype"):
        depth_normals(depth, o, d, valid.float())
    bad = depth.clone()
    bad[2, 3] = float("nan")
    with pytest.raises(ValueError, match="depth"):
        depth_normals(bad, o, d, valid)
    with pytest.raises(ValueError, match="eps"):
        depth_normals(depth, o, d, valid, eps=-1.0)
