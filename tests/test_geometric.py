# SPDX-License-Identifier: Apache-2.0
"""Forward-backward depth reprojection term (:mod:`wtopo.fitting.geometric`): the round trip
closes on true depth maps (pinhole and barrel lens), matches a float64 NumPy round trip through
:meth:`wtopo.camera.Camera.project` pixel by pixel, a wrong reference depth costs and its gradient
points back to the truth, occluded or unseen pixels carry nothing, and a fit with the term
records it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from fit_configs import fit_with_loss_term
from lenses import barrel_twin

from wtopo import scenes
from wtopo.camera import Camera
from wtopo.fitting.geometric import ForwardBackwardDepth


@pytest.fixture(scope="module")
def plane():
    """A hemisphere of 8 views around a tilted quad (z = 0.3 x)."""
    quad = trimesh.Trimesh([[-1, -1, -0.3], [1, -1, 0.3], [1, 1, 0.3], [-1, 1, -0.3]], [[0, 1, 2], [0, 2, 3]],
                           process=False)
    return scenes.from_mesh(quad, n_views=8, resolution=(96, 72), rig="hemisphere", texture="flat",
                            background="black", seed=1)


def _truth(cam: Camera, dtype=torch.float32):
    """z-depth [H, W] of the unbounded plane z = 0.3 x along the camera's pixel rays (pixel_rays'
    dirs have camera z = 1, so the ray parameter is the z-depth) and full alpha where the ray meets it
    in front of the camera (the term reads only the cameras of the scene, not its pictures)."""
    o, d = cam.pixel_rays(dtype=torch.float64)
    t = -(o[..., 2] - 0.3 * o[..., 0]) / (d[..., 2] - 0.3 * d[..., 0])
    on = t > 0
    return torch.where(on, t, torch.zeros_like(t)).to(dtype), on.to(dtype)


def _term(cams, **kw):
    return ForwardBackwardDepth(cams, np.zeros(3), pixels=kw.pop("pixels", 3000), seed=0, **kw)


def _pair(term, cams, it=0, vi=0):
    nj = term.neighbour(it, vi)
    return nj, _truth(cams[vi]), _truth(cams[nj])


def test_round_trip_closes_on_true_depth(plane):
    cams = plane.cameras
    fb = _term(cams)
    nj, (d, a), (dn, an) = _pair(fb, cams)
    err, valid = fb.errors(0, 0, d, a, nj, dn, an)
    assert int(valid.sum()) > 1000, "too few pixels measured"
    # measured: median 0.002 px, 99th percentile 0.02 px (float32, bilinear depth on a plane is exact
    # away from the quad's edge, where the neighbour's depth steps to 0 and its alpha to 0.5 or less)
    assert float(err[valid].median()) < 0.01
    assert float(torch.quantile(err[valid], 0.95)) < 0.05
    assert float(fb(0, 0, d, a, nj, dn, an)) < 0.01


def test_errors_match_a_float64_numpy_round_trip(plane):
    """Independent of the term's torch cameras: NumPy float64 through Camera.project and
    Camera.pixel_rays, bilinear depth by hand, on a reference depth 3 % too far."""
    cams = plane.cameras
    fb = _term(cams, pixels=500)
    nj, (d, a), (dn, an) = _pair(fb, cams)
    err, valid = fb.errors(0, 0, d * 1.03, a, nj, dn, an)
    g = torch.Generator(d.device).manual_seed(fb._seed(0))  # the term's own draw
    py = torch.randint(0, cams[0].height, (500,), generator=g).numpy()
    px = torch.randint(0, cams[0].width, (500,), generator=g).numpy()
    o, r = (x.numpy() for x in cams[0].pixel_rays(dtype=torch.float64))
    on, rn = (x.numpy() for x in cams[nj].pixel_rays(dtype=torch.float64))
    dn64 = _truth(cams[nj], torch.float64)[0].numpy()
    x = o[py, px] + r[py, px] * (1.03 * _truth(cams[0], torch.float64)[0].numpy()[py, px])[:, None]
    uv, _ = cams[nj].project(x)
    checked = 0
    for k in np.flatnonzero(valid.numpy()):
        u, v = uv[k] - 0.5  # pixel centres at +0.5
        i0, j0 = int(np.floor(v)), int(np.floor(u))
        if not (0 <= i0 < cams[nj].height - 1 and 0 <= j0 < cams[nj].width - 1):
            continue
        fy, fx = v - i0, u - j0
        corner = dn64[i0:i0 + 2, j0:j0 + 2]
        if (corner <= 0).any():  # the quad's edge: the term's bilinear alpha decides, skip
            continue
        wts = np.array([[(1 - fy) * (1 - fx), (1 - fy) * fx], [fy * (1 - fx), fy * fx]])
        o_q, r_q = (np.tensordot(wts, m[i0:i0 + 2, j0:j0 + 2], axes=([0, 1], [0, 1])) for m in (on, rn))
        y = o_q + r_q * (wts * corner).sum()
        p, _ = cams[0].project(y[None])
        ref = np.hypot(p[0, 0] - (px[k] + 0.5), p[0, 1] - (py[k] + 0.5))
        assert abs(float(err[k]) - ref) < 2e-3 + 1e-3 * ref, (k, float(err[k]), ref)
        checked += 1
    assert checked > 100, f"only {checked} pixels compared"
    # 3 % too deep is several pixels of parallax on this rig: the round trip opens
    assert float(err[valid].median()) > 0.5


@pytest.mark.parametrize("scale, sign", [(1.004, 1.0), (0.996, -1.0)])
def test_a_wrong_depth_costs_and_its_gradient_points_to_the_truth(plane, scale, sign):
    cams = plane.cameras
    fb = _term(cams)
    nj, (d, a), (dn, an) = _pair(fb, cams)
    s = torch.tensor(scale, requires_grad=True)
    loss = fb(0, 0, d * s, a, nj, dn, an)
    loss.backward()
    # measured: 0.19 px at 0.4 % off the depth (the term's 1 px cut keeps most pixels)
    assert float(loss) > 0.05, "the term does not see a 0.4 % depth error"
    assert sign * float(s.grad) > 0, f"d loss / d scale = {float(s.grad):.4g} at scale {scale}"


def test_float64_finite_difference_of_the_reference_depth(plane):
    """The round-trip errors' gradient w.r.t. a global depth scale against central differences, in
    float64 (the term itself weights by a detached exp(-error), so its value's derivative is not its
    gradient by design: the check is on the errors it is built from)."""
    cams = plane.cameras
    fb = _term(cams, pixels=800)
    nj, _, _ = _pair(fb, cams)
    d, a = _truth(cams[0], torch.float64)
    dn, an = _truth(cams[nj], torch.float64)
    _, keep = fb.errors(0, 0, d * 1.003, a, nj, dn, an)

    def f(s):
        return fb.errors(0, 0, d * s, a, nj, dn, an)[0][keep].sum()

    s = torch.tensor(1.003, dtype=torch.float64, requires_grad=True)
    f(s).backward()
    h = 1e-7
    with torch.no_grad():
        fd = (float(f(torch.tensor(1.003 + h, dtype=torch.float64)))
              - float(f(torch.tensor(1.003 - h, dtype=torch.float64)))) / (2 * h)
    assert int(keep.sum()) > 500 and abs(fd) > 1.0, "the errors do not depend on the depth"
    assert abs(float(s.grad) - fd) < 1e-4 * abs(fd), (float(s.grad), fd)


def test_distorted_rig_closes_like_its_pinhole_twin(plane):
    cams, _ = barrel_twin(plane)
    fb = _term(cams)
    nj, (d, a), (dn, an) = _pair(fb, cams)
    err, valid = fb.errors(0, 0, d, a, nj, dn, an)
    assert int(valid.sum()) > 1000
    # measured: median 0.003 px through the barrel lens (the neighbour's rays are bilinear in the pixel)
    assert float(err[valid].median()) < 0.02
    off, ok = fb.errors(0, 0, d * 1.03, a, nj, dn, an)
    assert float(off[ok].median()) > 0.5


def test_occluded_unseen_and_lone_views_carry_nothing(plane):
    cams = plane.cameras
    fb = _term(cams)
    nj, (d, a), (dn, an) = _pair(fb, cams)
    occluder = dn * 0.5  # the neighbour sees something else, far in front: errors of many pixels
    dd = d.clone().requires_grad_(True)
    loss = fb(0, 0, dd, a, nj, occluder, an)
    loss.backward()
    assert float(loss) == 0.0 and float(dd.grad.abs().sum()) == 0.0
    assert float(fb(0, 0, d, a, nj, dn, torch.zeros_like(an))) == 0.0  # the neighbour renders nothing there
    assert float(fb(0, 0, d, torch.zeros_like(a), nj, dn, an)) == 0.0  # the reference renders nothing
    lone = _term(cams[:1])
    assert not lone.has_neighbours(0)


def test_bad_arguments_are_named(plane):
    with pytest.raises(ValueError, match="pixels"):
        ForwardBackwardDepth(plane.cameras, np.zeros(3), pixels=0)
    with pytest.raises(ValueError, match="max_error"):
        ForwardBackwardDepth(plane.cameras, np.zeros(3), max_error=0.0)


def test_a_fit_with_the_term_records_it():
    """The term joins the fit from the multi-view start fraction, finite, and the fit still meshes."""
    geo, res = fit_with_loss_term("geometric", multiview_geometric=0.03, multiview_start_fraction=0.3)
    assert geo, "the geometric term never ran"
    assert all(np.isfinite(v) and v >= 0 for v in geo) and max(geo) > 0
    assert len(res.mesh.faces) > 0
