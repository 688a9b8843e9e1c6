# SPDX-License-Identifier: Apache-2.0
"""The two-view support of the mesh terms' pixels (:mod:`wtopo.fitting.view_support`): analytic cases on
a plane seen by cameras looking straight down, occlusion, the depth tolerance, missing views, and a
brute-force per-pixel reference on random depth maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from wtopo.camera import Camera
from wtopo.fitting.view_support import ViewSupport

_FOV = math.radians(60.0)
_H = 2.0  # cameras' height above the plane z = 0


def _down(x: float, size: int = 32) -> Camera:
    """A camera at (x, 0, 2) looking straight down at the plane z = 0 (z-depth 2 at every pixel)."""
    return Camera.look_at([x, 0.0, _H], [x, 0.0, 0.0], [0.0, 1.0, 0.0], fov_x=_FOV, width=size, height=size)


def _plane_maps(cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.full((cam.height, cam.width), _H, dtype=torch.float32),
            torch.ones(cam.height, cam.width, dtype=torch.float32))


def _pixel_x(cam: Camera) -> np.ndarray:
    """World x [H, W] of each pixel centre's point on the plane."""
    o, d = cam.pixel_rays(torch.device("cpu"), torch.float64)
    return (o + d * _H)[..., 0].numpy()


def test_plane_is_supported_where_the_other_view_sees_it():
    """Two parallel cameras 0.5 apart: a pixel of the first is supported exactly where its plane point falls
    inside the second camera's image (x >= 0.5 - 2 tan(30 deg)), which leaves a strip of the first unsupported."""
    a, b = _down(0.0), _down(0.5)
    vs = ViewSupport([a, b], min_views=2, center=np.zeros(3))
    vs.remember(1, *_plane_maps(b))
    depth, _ = _plane_maps(a)
    mask = torch.ones(a.height, a.width, dtype=torch.bool)
    got = vs.supported(0, depth, mask, 1e-3).numpy()
    want = _pixel_x(a) >= 0.5 - _H * math.tan(_FOV / 2)
    assert 0 < (~want).sum() < want.sum()  # the case exercises both outcomes
    np.testing.assert_array_equal(got, want)
    counts = vs.take_counts()
    assert counts["compared"] == a.width * a.height and counts["unsupported"] == int((~want).sum())
    assert vs.take_counts()["compared"] == 0


def test_occluded_and_off_surface_points_are_not_seen():
    """A nearer surface in the other view (a block rendered at depth 1) hides the plane there; a point off
    the other view's surface by more than the tolerance is not seen, within it is; a transparent pixel of
    the other view sees nothing."""
    a, b = _down(0.0), _down(0.0)  # the same viewpoint: pixel p of a lands on pixel p of b
    vs = ViewSupport([a, b], min_views=2, center=np.zeros(3))
    db, ab = _plane_maps(b)
    db[:8] = 1.0  # an occluder over the first 8 rows
    ab[:, :4] = 0.2  # the first 4 columns rendered transparent
    db[20:, :] = _H + 0.05  # 5 cm behind the point from row 20 on
    vs.remember(1, db, ab)
    depth, _ = _plane_maps(a)
    mask = torch.ones(a.height, a.width, dtype=torch.bool)
    tight = vs.supported(0, depth, mask, 0.01)
    loose = vs.supported(0, depth, mask, 0.1)
    assert not tight[:8].any() and not loose[:8].any()
    assert not tight[:, :4].any() and not loose[:, :4].any()
    assert tight[8:20, 4:].all() and not tight[20:].any()
    assert loose[8:, 4:].all()


def test_per_pixel_tolerance():
    """A tolerance map [H, W] applies pixel by pixel: the other view's surface 5 cm behind the point is seen
    from the rows given 0.1 and not from those given 0.01; a scalar tensor acts as the number."""
    a, b = _down(0.0), _down(0.0)
    vs = ViewSupport([a, b], min_views=2, center=np.zeros(3))
    db, ab = _plane_maps(b)
    vs.remember(1, db + 0.05, ab)
    depth, _ = _plane_maps(a)
    mask = torch.ones(a.height, a.width, dtype=torch.bool)
    tol = torch.full((a.height, a.width), 0.01)
    tol[:10] = 0.1
    got = vs.supported(0, depth, mask, tol)
    assert got[:10].all() and not got[10:].any()
    assert torch.equal(vs.supported(0, depth, mask, torch.tensor(0.1)), mask)


def test_min_views_mask_and_missing_views():
    """Three views of the plane: min_views 3 needs both others; pixels off the mask come back False; a view
    with no kept maps is rendered through the callback once and kept, and without a callback it does not count."""
    cams = [_down(0.0), _down(0.05), _down(-0.05)]
    depth, _ = _plane_maps(cams[0])
    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[10:22, 10:22] = True
    vs = ViewSupport(cams, min_views=3, center=np.zeros(3))
    vs.remember(1, *_plane_maps(cams[1]))
    assert not vs.supported(0, depth, mask, 1e-3).any()  # view 2 unknown and no way to render it
    calls = []

    def render(u):
        calls.append(u)
        return _plane_maps(cams[u])

    got = vs.supported(0, depth, mask, 1e-3, render=render)
    assert calls == [2]
    assert torch.equal(got, mask)
    assert torch.equal(vs.supported(0, depth, mask, 1e-3, render=render), mask) and calls == [2]
    empty = torch.zeros_like(mask)
    assert not vs.supported(0, depth, empty, 1e-3).any()


def test_arguments():
    cams = [_down(0.0), _down(0.5)]
    with pytest.raises(ValueError, match="min_views"):
        ViewSupport(cams, min_views=1, center=np.zeros(3))
    with pytest.raises(ValueError, match="cameras"):
        ViewSupport(cams[:1], min_views=2, center=np.zeros(3))


def _reference(cams, vi, depth, mask, maps, tol, min_views):
    """Per-pixel loop of the rule in float64 (the module's docstring), over every other view."""
    H, W = depth.shape
    o, d = cams[vi].pixel_rays(torch.device("cpu"), torch.float64)
    out = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            if not mask[y, x]:
                continue
            X = (o[y, x] + d[y, x] * float(depth[y, x])).numpy()
            n = 1
            for u, (du, au) in maps.items():
                if u == vi:
                    continue
                c = cams[u]
                p = c.world_to_camera[:3, :3] @ X + c.world_to_camera[:3, 3]
                if p[2] <= 0:
                    continue
                uu = c.K[0, 0] * p[0] / p[2] + c.K[0, 1] * p[1] / p[2] + c.K[0, 2]
                vv = c.K[1, 1] * p[1] / p[2] + c.K[1, 2]
                ix, iy = math.floor(uu), math.floor(vv)
                if not (0 <= ix < c.width and 0 <= iy < c.height):
                    continue
                if au[iy, ix] >= 0.5 and du[iy, ix] > 0 and abs(p[2] - float(du[iy, ix])) <= tol:
                    n += 1
            out[y, x] = n >= min_views
    return out


@pytest.mark.parametrize("min_views", [2, 3])
def test_matches_the_reference_on_random_views(min_views):
    """Four views around a bumpy surface with noisy depth maps: the module equals the per-pixel reference
    (float64 depths, so no pixel sits on a rounding boundary by chance), with both outcomes present."""
    g = torch.Generator().manual_seed(3)
    cams = [Camera.look_at([2 * math.cos(a), 2 * math.sin(a), 1.0], [0, 0, 0], [0, 0, 1], fov_x=_FOV, width=20,
                           height=16) for a in np.linspace(0, 1.2, 4)]
    maps = {}
    for u, c in enumerate(cams):
        base = 2.2 + 0.1 * torch.rand(c.height, c.width, generator=g, dtype=torch.float64)
        alpha = (torch.rand(c.height, c.width, generator=g, dtype=torch.float64) > 0.2).to(torch.float64)
        maps[u] = (base, alpha)
    vs = ViewSupport(cams, min_views=min_views, center=np.zeros(3))
    for u in (1, 2, 3):
        vs.remember(u, *maps[u])
    depth = maps[0][0]
    mask = maps[0][1] > 0
    got = vs.supported(0, depth, mask, 0.05).numpy()
    want = _reference(cams, 0, depth, mask.numpy(), {u: (m[0].numpy(), m[1].numpy()) for u, m in maps.items()},
                      0.05, min_views)
    assert want.any() and (mask.numpy() & ~want).any()
    np.testing.assert_array_equal(got, want)
