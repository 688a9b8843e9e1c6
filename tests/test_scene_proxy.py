# SPDX-License-Identifier: Apache-2.0
"""A scene's proxy mesh: a ground the region of interest cuts, under a closed part, with the local zero level
and the clip to the region (``mesh.level_sigma``, ``mesh.clip_to_region``)."""

import math

import numpy as np
import torch

from wtopo.fitting.config import MeshConfig
from wtopo.fitting.proxy import ProxyMesh
from wtopo.fitting.surfels import Surfels

GROUND_Z = 0.2
ROI = (np.array([0.1, 0.1, 0.15]), np.array([0.9, 0.9, 0.9]))  # the region of interest in the unit box
BALL = (np.array([0.5, 0.5, 0.5]), 0.2)


def _ground_and_ball(ball_opacity=0.9, ground_opacity=0.9):
    """Surfels of a ground z = GROUND_Z across the region (normals up) and of a sphere over it (outward):
    the ground ends at the region's sides, as a scene's ground outside the region carries no Poisson weight."""
    g = torch.Generator().manual_seed(0)
    side = torch.linspace(0.1, 0.9, 48)
    gx, gy = torch.meshgrid(side, side, indexing="ij")
    ground = torch.stack([gx.flatten(), gy.flatten(), torch.full((48 * 48,), GROUND_Z)], dim=1)
    d = torch.randn(2500, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    ball = torch.as_tensor(BALL[0], dtype=torch.float32) + BALL[1] * d
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand_as(ground)
    pts, nrm = torch.cat([ground, ball]), torch.cat([up, d])
    s = Surfels.from_points(pts, torch.full_like(pts, 0.5), normals=nrm, scales=torch.full((len(pts),), 0.008))
    op = torch.cat([torch.full((len(ground),), ground_opacity), torch.full((len(ball),), ball_opacity)])
    with torch.no_grad():
        s.params["opacity_logits"].copy_(torch.log(op / (1 - op)))
    return s


def _faces(pm):
    return pm.verts.detach()[pm.faces.long()].mean(dim=1).numpy()


def test_clip_drops_the_closing_outside_the_region_and_keeps_the_ground():
    """Unclipped, the proxy of a cut ground has faces outside the region (the periodic image of the ground
    over it); clipped, every face lies within a cell of the region, the ground covers it from one side to
    the other within a cell of its height, and the sphere's top is kept. ``with_resolution`` keeps the clip."""
    s = _ground_and_ball()
    cfg = MeshConfig(resolution=64, level_sigma=2.0)
    free = ProxyMesh(cfg).build(s)
    c = _faces(free)
    h = ProxyMesh(cfg).cell
    outside = ~np.all((c >= ROI[0] - h) & (c <= ROI[1] + h), axis=1)
    assert outside.sum() > 100
    clipped = ProxyMesh(cfg, clip=ROI)
    for proxy in (clipped, clipped.with_resolution(96)):
        pm = proxy.build(s)
        c = _faces(pm)
        assert np.all((c >= ROI[0] - proxy.cell - 1e-6) & (c <= ROI[1] + proxy.cell + 1e-6))
        # the ground: faces within a cell of its height over the region's corners, far from the sphere's foot
        r = np.linalg.norm(c[:, :2] - BALL[0][:2], axis=1)
        ground = (np.abs(c[:, 2] - GROUND_Z) < proxy.cell) & (r > BALL[1] + 0.05)
        for corner in ((0.2, 0.2), (0.8, 0.2), (0.2, 0.8), (0.8, 0.8)):
            assert (np.linalg.norm(c[ground, :2] - np.array(corner), axis=1) < 0.05).sum() > 10, corner
        top = c[:, 2] > BALL[0][2] + 0.1
        assert top.sum() > 50
        assert np.abs(np.linalg.norm(c[top] - BALL[0], axis=1) - BALL[1]).max() < 2 * proxy.cell


def test_local_level_keeps_the_ground_beside_a_closed_part():
    """Ground surfels at about half the sphere's opacity (the Poisson weights): with one global level (the
    sphere's, mostly) the clipped proxy has no face within a cell of the ground away from the sphere's foot
    (it closes a pillow under it); with the local level the ground is there. The proxy stays
    differentiable w.r.t. the ground's surfels."""
    s = _ground_and_ball(ball_opacity=0.95, ground_opacity=0.5)
    counts = {}
    for ls in (0.0, 2.0):
        proxy = ProxyMesh(MeshConfig(resolution=64, level_sigma=ls), clip=ROI)
        pm = proxy.build(s)
        c = _faces(pm)
        r = np.linalg.norm(c[:, :2] - BALL[0][:2], axis=1)
        counts[ls] = int(((np.abs(c[:, 2] - GROUND_Z) < proxy.cell) & (r > BALL[1] + 0.05)).sum())
        if ls > 0:
            loss = pm.verts[:, 2].sum()
            (g,) = torch.autograd.grad(loss, s.params["means"])
            assert math.isfinite(float(g.abs().sum())) and float(g[: 48 * 48].abs().sum()) > 0
    assert counts[2.0] > 2000, counts
    assert counts[0.0] < 0.25 * counts[2.0], counts


def test_background_outside_the_region_stays_out_of_the_solve():
    """Surfels outside the region (two cells and more: a scene's background, never oriented by a mesh) change
    nothing in the clipped proxy, where the unclipped one moves."""
    s = _ground_and_ball()
    g = torch.Generator().manual_seed(5)
    junk = torch.rand(400, 3, generator=g) * 0.1 + torch.tensor([0.95, 0.5, 0.5])  # past the region's +x side
    both = Surfels.from_points(torch.cat([s.means.detach(), junk]), torch.full((len(s) + 400, 3), 0.5),
                               normals=torch.cat([torch.zeros(len(s), 3), torch.randn(400, 3, generator=g)]),
                               scales=torch.full((len(s) + 400,), 0.008))
    with torch.no_grad():
        for k in ("quats", "log_scales", "opacity_logits"):
            both.params[k][: len(s)] = s.params[k]
        both.params["opacity_logits"][len(s):] = 3.0
    cfg = MeshConfig(resolution=64, level_sigma=2.0)
    assert ProxyMesh(cfg).cell * 2 < 0.95 - ROI[1][0]
    a, b = ProxyMesh(cfg, clip=ROI).build(s), ProxyMesh(cfg, clip=ROI).build(both)
    assert torch.equal(a.faces, b.faces) and torch.allclose(a.verts, b.verts, atol=1e-6)
    fa, fb = ProxyMesh(cfg).build(s), ProxyMesh(cfg).build(both)
    assert fa.faces.shape != fb.faces.shape or not torch.allclose(fa.verts, fb.verts, atol=1e-4)
