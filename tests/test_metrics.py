# SPDX-License-Identifier: Apache-2.0
"""Metrics against shapes and images with known answers."""

import math

import numpy as np
import pytest
import torch
import trimesh
from skimage.metrics import structural_similarity

from wtopo import metrics

N_SAMPLES = 40_000
# Sampling noise of a mean over 40k area samples is ~1e-3 of the measured spread; tessellation of a
# level-5 icosphere moves its surface by <= 2e-4 of the radius.  2e-3 covers both with room.
MEAN_TOL = 2e-3
# Fractions (precision / recall) over 40k samples: binomial std <= 2.5e-3; 4 sigma plus tessellation.
FRACTION_TOL = 1.2e-2
EXACT_TOL = 1e-9  # exact-distance cases (planar faces): only float64 rounding


def _sphere(radius=1.0, center=(0, 0, 0), sub=5):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    m.apply_translation(center)
    return m


def _box(side, center=(0, 0, 0)):
    m = trimesh.creation.box(extents=(side, side, side))
    m.apply_translation(center)
    return m


def test_identical_meshes_give_zero_distance_and_full_f_score():
    """Score a mesh against itself: chamfer 0, F = 1, normal consistency 1."""
    m = _sphere(sub=3)
    r = metrics.chamfer(m, m, n_samples=5000)
    assert r.chamfer < EXACT_TOL and r.chamfer_rel < EXACT_TOL
    f = metrics.f_score(m, m, 1e-6, n_samples=5000)
    assert (f.precision, f.recall, f.f_score) == (1.0, 1.0, 1.0)
    assert metrics.normal_consistency(m, m, n_samples=5000) == pytest.approx(1.0, abs=1e-9)


def test_concentric_boxes_match_closed_form():
    """Compare chamfer of concentric cubes (side 2 and 2.4) with an independent quadrature."""
    a, b = _box(2.0), _box(2.4)
    r = metrics.chamfer(a, b, n_samples=N_SAMPLES)
    # a -> b: every point of the inner cube is exactly 0.2 from the outer one
    np.testing.assert_allclose(r.accuracy, 0.2, atol=EXACT_TOL)
    # b -> a: point (x, y, 1.2) on an outer face is sqrt(max(|x|-1,0)^2 + max(|y|-1,0)^2 + 0.2^2) away
    g = (np.arange(2000) + 0.5) / 2000 * 2.4 - 1.2
    x, y = np.meshgrid(g, g)
    d = np.sqrt(np.maximum(np.abs(x) - 1, 0) ** 2 + np.maximum(np.abs(y) - 1, 0) ** 2 + 0.04)
    np.testing.assert_allclose(r.completeness, d.mean(), atol=MEAN_TOL * 0.2)
    np.testing.assert_allclose(r.diagonal, 2.4 * math.sqrt(3), rtol=1e-12)
    np.testing.assert_allclose(r.chamfer_rel, 0.5 * (0.2 + d.mean()) / (2.4 * math.sqrt(3)), rtol=MEAN_TOL)


def _offset_sphere_distance_mean(delta):
    # distance from p on the unit sphere to the unit sphere centred delta along z: |sqrt(1+d^2-2dz) - 1|;
    # area is uniform in z on a sphere (Archimedes), so average over z in [-1, 1]
    z = (np.arange(200_000) + 0.5) / 200_000 * 2 - 1
    return np.abs(np.sqrt(1 + delta ** 2 - 2 * delta * z) - 1).mean()


def test_offset_spheres_match_closed_form():
    """Compare chamfer, F-score and normals of two offset unit spheres with closed forms."""
    delta, tau = 0.3, 0.1
    a, b = _sphere(), _sphere(center=(0, 0, delta))
    r = metrics.chamfer(a, b, n_samples=N_SAMPLES)
    want = _offset_sphere_distance_mean(delta)
    np.testing.assert_allclose([r.accuracy, r.completeness, r.chamfer], want, atol=MEAN_TOL)
    # |p - c| in [1 - tau, 1 + tau]  <=>  z in [(d^2 - 2 tau - tau^2) / 2d, (d^2 + 2 tau - tau^2) / 2d]
    z_lo = (delta ** 2 - 2 * tau - tau ** 2) / (2 * delta)
    z_hi = (delta ** 2 + 2 * tau - tau ** 2) / (2 * delta)
    frac = (min(z_hi, 1) - max(z_lo, -1)) / 2
    f = metrics.f_score(a, b, tau, n_samples=N_SAMPLES)
    np.testing.assert_allclose([f.precision, f.recall, f.f_score], frac, atol=FRACTION_TOL)
    # concentric spheres 0.1 apart: nothing within 0.05, everything within 0.15
    c, d = _sphere(sub=4), _sphere(1.1, sub=4)
    assert metrics.f_score(c, d, 0.05, n_samples=5000).f_score == 0.0
    assert metrics.f_score(c, d, 0.15, n_samples=5000).f_score == 1.0
    # concentric: closest-face normals are the same radial direction
    assert metrics.normal_consistency(c, d, n_samples=5000) > 0.999


def test_point_to_surface_distance_matches_trimesh():
    """Check the exact point-to-triangle distance against trimesh's closest-point query."""
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(3000, 3, 3))
    p = rng.normal(size=(3000, 3)) * 2
    from wtopo.metrics._surface import _closest_on_triangles

    ours = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    np.testing.assert_allclose(ours, trimesh.triangles.closest_point(tri, p), atol=1e-12)


def test_cube_and_subdivision():
    """Compare a cube with its 1-to-4 subdivision: same surface, known vertex distances and topology."""
    a = _box(2.0)
    v, f = trimesh.remesh.subdivide(a.vertices, a.faces)
    b = trimesh.Trimesh(v, f, process=False)
    assert metrics.chamfer(a, b, n_samples=5000).chamfer < EXACT_TOL
    r = metrics.chamfer_vertices(a, b)
    # 26 vertices: 8 corners (0), 12 cube-edge midpoints (1 from a corner), 6 face centres (sqrt 2)
    np.testing.assert_allclose(r.accuracy, 0.0, atol=EXACT_TOL)
    np.testing.assert_allclose(r.completeness, (12 + 6 * math.sqrt(2)) / 26, rtol=1e-12)
    sa, sb = metrics.mesh_stats(a), metrics.mesh_stats(b)
    assert (sa["n_vertices"], sa["n_edges"], sa["n_faces"], sa["euler"]) == (8, 18, 12, 2)
    assert (sb["n_vertices"], sb["n_edges"], sb["n_faces"], sb["euler"]) == (26, 72, 48, 2)
    for s in (sa, sb):
        assert s["watertight"] and s["winding_consistent"] and s["n_components"] == 1 and s["genus"] == 0
        np.testing.assert_allclose(s["area"], 24.0, rtol=1e-12)
        np.testing.assert_allclose(s["volume"], 8.0, rtol=1e-12)


def test_mesh_stats_topology_cases():
    """Count boundary edges, components and genus of open, split and toroidal meshes."""
    s = _sphere(sub=2)
    open_ = trimesh.Trimesh(s.vertices, s.faces[1:], process=False)
    st = metrics.mesh_stats(open_)
    assert st["boundary_edges"] == 3 and not st["watertight"] and st["volume"] is None and st["euler"] == 1
    two = trimesh.util.concatenate([_sphere(sub=1), _sphere(center=(5, 0, 0), sub=1)])
    st = metrics.mesh_stats(two)
    assert st["n_components"] == 2 and st["euler"] == 4 and st["genus"] is None
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    st = metrics.mesh_stats(torus)
    assert st["watertight"] and st["euler"] == 0 and st["genus"] == 1
    flipped = trimesh.Trimesh(s.vertices, np.concatenate([s.faces[:1, ::-1], s.faces[1:]]), process=False)
    assert not metrics.mesh_stats(flipped)["winding_consistent"]


def test_psnr_known_values(device):
    """Check PSNR of a constant offset (20 dB for 0.1) and with a mask."""
    t = torch.rand(2, 16, 20, 3, device=device) * 0.8
    p = t + 0.1
    np.testing.assert_allclose(metrics.psnr(p, t).item(), 20.0, rtol=1e-5)
    m = torch.zeros(2, 16, 20, dtype=torch.bool, device=device)
    m[:, :8] = True
    p2 = t.clone()
    p2[:, :8] += 0.01
    p2[:, 8:] += 0.5  # outside the mask: ignored
    np.testing.assert_allclose(metrics.psnr(p2, t, mask=m).item(), 40.0, rtol=1e-4)
    assert metrics.psnr(t[0], t[0]).item() == math.inf


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_matches_skimage(dtype, device):
    """Compare SSIM (Gaussian 11 / 1.5, K1 0.01, K2 0.03) with scikit-image and check its gradient."""
    g = torch.Generator().manual_seed(0)
    t = torch.rand(24, 30, 3, generator=g, dtype=dtype)
    p = (t + 0.1 * torch.randn(24, 30, 3, generator=g, dtype=dtype)).clamp(0, 1)
    t, p = t.to(device), p.to(device).requires_grad_(True)
    ours = metrics.ssim(p, t)
    ref = structural_similarity(p.detach().cpu().numpy(), t.cpu().numpy(), gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    np.testing.assert_allclose(ours.item(), ref, rtol=1e-5 if dtype == torch.float32 else 1e-10)
    ours.backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    np.testing.assert_allclose(metrics.ssim(t, t).item(), 1.0, rtol=1e-6)
    batch = torch.stack([t, t.flip(0)])
    np.testing.assert_allclose(metrics.ssim(batch, batch).item(), 1.0, rtol=1e-6)


def test_metric_argument_errors():
    """Reject malformed meshes, thresholds and images with named ValueErrors."""
    m = _sphere(sub=1)
    with pytest.raises(ValueError, match="tau"):
        metrics.f_score(m, m, 0.0)
    with pytest.raises(ValueError, match="faces"):
        metrics.chamfer((m.vertices, m.faces + 1000), m)
    with pytest.raises(ValueError, match="area"):
        metrics.chamfer((np.zeros((3, 3)), np.array([[0, 1, 2]])), m)
    with pytest.raises(ValueError, match="same shape"):
        metrics.psnr(torch.rand(4, 4, 3), torch.rand(5, 4, 3))
    with pytest.raises(ValueError, match="at least 11x11"):
        metrics.ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3))


# -- region of interest and camera clearance ------------------------------------------------------
def _plane(half, z=0.0, cells=4):
    """Square plane [-half, half]^2 at height z, split into cells x cells quads."""
    g = np.linspace(-half, half, cells + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    f = np.concatenate([np.stack([a, a + cells + 1, a + cells + 2], 1), np.stack([a, a + cells + 2, a + 1], 1)])
    return trimesh.Trimesh(v, f, process=False)


ROI_SAMPLES = 20_000
# Fractions over 20k samples: binomial std <= 3.6e-3; 4 sigma.
ROI_FRACTION_TOL = 1.5e-2
ROI_BOX = ([-0.5, -0.5, -0.1], [0.5, 0.5, 0.1])


def test_roi_f_score_shifted_plane():
    """Score a plane shifted by delta against a larger plane: distances are delta, F flips at tau = delta."""
    gt, delta = _plane(2.0), 0.01
    pred = _plane(1.0, z=delta)
    hit = metrics.roi_f_score(pred, gt, *ROI_BOX, 1.5 * delta, n_samples=ROI_SAMPLES)
    np.testing.assert_allclose([hit.accuracy, hit.completeness], delta, atol=EXACT_TOL)
    assert (hit.precision, hit.recall, hit.f_score) == (1.0, 1.0, 1.0)
    assert hit.n_pred == hit.n_gt == ROI_SAMPLES  # in-box sampling reaches the count through rejection
    miss = metrics.roi_f_score(pred, gt, *ROI_BOX, 0.5 * delta, n_samples=ROI_SAMPLES)
    assert (miss.precision, miss.recall, miss.f_score) == (0.0, 0.0, 0.0)


def test_roi_f_score_half_covered_box():
    """Recall is the covered share of the in-box ground truth: a prediction over x < 0 gives 0.5 + tau."""
    gt, tau = _plane(2.0), 0.02
    v = np.array([[-1.0, -1, 0], [0, -1, 0], [0, 1, 0], [-1, 1, 0]])
    pred = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    r = metrics.roi_f_score(pred, gt, *ROI_BOX, tau, n_samples=ROI_SAMPLES)
    assert r.precision == 1.0
    np.testing.assert_allclose(r.recall, 0.5 + tau, atol=ROI_FRACTION_TOL)
    np.testing.assert_allclose(r.f_score, 2 * r.recall / (1 + r.recall), rtol=1e-12)


def test_roi_f_score_measures_against_the_whole_ground_truth():
    """Score an inset cube inside a box that crops the gt cube's x faces away: precision stays 1."""
    gt, pred = _box(1.0), _box(0.96)  # faces at +-0.5 and +-0.48
    lo, hi = [-0.49, -1, -1], [0.49, 1, 1]  # pred's x faces inside, gt's outside the box
    r = metrics.roi_f_score(pred, gt, lo, hi, 0.025, n_samples=ROI_SAMPLES)
    assert r.precision == 1.0  # pred's x faces are 0.02 from gt faces that lie outside the box
    # gt strips within 0.005 of a cube edge (|other coordinate| > 0.495: 1 %) are farther than tau
    np.testing.assert_allclose(r.recall, 0.99, atol=ROI_FRACTION_TOL)
    np.testing.assert_allclose(r.accuracy, 0.02, atol=EXACT_TOL)
    assert r.completeness >= 0.02 - EXACT_TOL
    # the gt in the box is only the four strips of the y and z faces
    assert r.n_gt == ROI_SAMPLES


def test_roi_f_score_empty_prediction():
    """Score an empty prediction, and one outside the box, as precision 0 and recall 0."""
    gt = _plane(2.0)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    for pred in (empty, _plane(0.3, z=5.0)):
        r = metrics.roi_f_score(pred, gt, *ROI_BOX, 0.01, n_samples=1000)
        assert (r.precision, r.recall, r.f_score, r.n_pred) == (0.0, 0.0, 0.0, 0)
        assert r.accuracy == math.inf and r.n_gt == 1000


def test_roi_f_score_argument_errors():
    """Reject a box without ground truth, an inverted box and a bad tau."""
    gt = _plane(1.0)
    with pytest.raises(ValueError, match="no surface inside"):
        metrics.roi_f_score(gt, gt, [5, 5, 5], [6, 6, 6], 0.1, n_samples=100)
    with pytest.raises(ValueError, match="upper must exceed lower"):
        metrics.roi_f_score(gt, gt, [1, 0, 0], [0, 1, 1], 0.1, n_samples=100)
    with pytest.raises(ValueError, match="tau"):
        metrics.roi_f_score(gt, gt, *ROI_BOX, 0.0, n_samples=100)


def test_camera_clearance_point_to_triangle():
    """Measure exact distances to faces (interior, edge, far from every vertex) and inf for no mesh."""
    plane = _plane(1.0, cells=1)
    centers = np.array([[0.0, 0, 2], [3, 0, 1], [0.5, 0.5, -0.3]])
    np.testing.assert_allclose(metrics.camera_clearance(plane, centers), [2.0, math.sqrt(5.0), 0.3], atol=1e-6)
    big = trimesh.Trimesh([[-100.0, -100, 0], [100, -100, 0], [0, 100, 0]], [[0, 1, 2]], process=False)
    # vertices are ~100 away, the face 0.01
    np.testing.assert_allclose(metrics.camera_clearance(big, [[0.0, 0, 0.01]]), [0.01], rtol=1e-4)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert np.all(metrics.camera_clearance(empty, centers) == math.inf)
    with pytest.raises(ValueError, match="camera_centers"):
        metrics.camera_clearance(plane, np.zeros((2, 2)))


def test_inward_offset_of_concentric_boxes_and_shifted_cube():
    """A cube inside a larger one is inside by exactly the gap; one outside it by minus the gap; a shifted
    copy is half in, half out, with a mean near 0."""
    inner, outer = _box(2.0), _box(2.4)
    r = metrics.inward_offset(inner, outer, n_samples=N_SAMPLES)
    np.testing.assert_allclose([r.mean, r.median, r.inside], [0.2, 0.2, 1.0], atol=1e-9)
    r = metrics.inward_offset(outer, inner, n_samples=N_SAMPLES)
    # all outside; beyond the inner cube's edges the side of the closest face's plane is nearer than the gap.
    # A sample a few 1e-5 inside a side's plane is as near the side (float32 search) as the face under it: a
    # tie broken either way, counted inside by 1e-5 (3 of 40,000 samples here); far fewer than 1 in 1,000
    assert -0.2 - 1e-9 < r.mean < -0.15 and r.median == pytest.approx(-0.2) and r.inside < 1e-3
    shifted = _box(2.0, center=(0.1, 0.0, 0.0))
    r = metrics.inward_offset(shifted, _box(2.0), n_samples=N_SAMPLES)
    assert abs(r.mean) < 0.01 and 0.1 < r.inside < 0.5  # the x = -0.9 face in, x = 1.1 out, the rest on


def _top_cameras(xs=(-0.2, 0.2)):
    from wtopo.camera import Camera

    return [Camera.look_at((x, 0.0, 5.0), (0, 0, 0), (0, 1, 0), fov_x=math.radians(30.0), width=64, height=64)
            for x in xs]


def test_view_counts_see_only_the_faces_turned_to_the_cameras():
    """Two cameras high above a unit cube see its top face and nothing else (the sides are behind it)."""
    cube = _box(1.0)
    pts, fi = metrics.sample_surface(cube, 20_000, seed=3)
    top = pts[:, 2] > 0.5 - 1e-9
    counts = metrics.view_counts(pts, cube, _top_cameras(), tolerance=1e-4)
    assert top.sum() > 2000  # the case exercised both kinds of sample
    # below the top edge by more than float32's reach, a side is always behind the top face
    assert np.all(counts[top] == 2) and np.all(counts[pts[:, 2] < 0.5 - 1e-3] == 0)
    from wtopo.camera import Camera

    under = Camera.look_at((0, 0, -5.0), (0, 0, 0), (0, 1, 0), fov_x=math.radians(30.0), width=64, height=64)
    below = metrics.view_counts(pts, cube, _top_cameras((0.0,)) + [under], tolerance=1e-4)
    assert np.all(below[top] == 1) and np.all(below[pts[:, 2] < -0.5 + 1e-9] == 1)
    assert np.all(below[np.abs(pts[:, 2]) < 0.5 - 1e-3] == 0)


def test_observed_chamfer_leaves_out_the_unseen_truth_and_scores_floaters():
    """A box that matches the cube's seen top face but runs deeper below: the full Chamfer sees the
    difference, the observed one does not; a floater above the top face is scored."""
    cube = _box(1.0)
    deeper = trimesh.creation.box(extents=(1.0, 1.0, 1.4))
    deeper.apply_translation((0, 0, -0.2))  # z from -0.9 to 0.5: the same top face
    full = metrics.chamfer(deeper, cube, n_samples=N_SAMPLES)
    ob = metrics.observed_chamfer(deeper, cube, _top_cameras(), n_samples=N_SAMPLES)
    assert full.chamfer_rel > 0.01
    assert abs(ob.observed - 1 / 6) < FRACTION_TOL  # the top face's share of the cube's area
    assert 0 < ob.scored < 0.5 and ob.result.chamfer_rel < 1e-3
    assert ob.views.shape == (N_SAMPLES,)
    floater = trimesh.util.concatenate([cube, _sphere(0.1, (0, 0, 0.8), sub=3)])
    fl = metrics.observed_chamfer(floater, cube, _top_cameras(), n_samples=N_SAMPLES)
    assert fl.result.accuracy > 10 * ob.result.accuracy + 1e-3  # the floater's ~0.2 to the top face counts
    assert fl.result.completeness < 1e-6


def test_observed_chamfer_argument_errors():
    cube = _box(1.0)
    with pytest.raises(ValueError, match="min_views"):
        metrics.observed_chamfer(cube, cube, _top_cameras(), min_views=0)
    with pytest.raises(ValueError, match="cameras"):
        metrics.observed_chamfer(cube, cube, [])
    with pytest.raises(ValueError, match="seen by 3"):
        metrics.observed_chamfer(cube, cube, _top_cameras(), min_views=3)
    with pytest.raises(ValueError, match="tolerance"):
        metrics.view_counts(np.zeros((1, 3)), cube, _top_cameras(), tolerance=0.0)
    with pytest.raises(ValueError, match="tolerance"):
        metrics.observed_chamfer(cube, cube, _top_cameras(), tolerance=float("nan"))


def test_closest_faces_and_ray_hits_match_embree():
    """The metrics' BVH queries (closest face, first ray hit) against Open3D's Embree scene as an independent
    reference: the same faces and hits on a sphere's samples, the same analytic mean distance."""
    o3d = pytest.importorskip("open3d")
    from wtopo.metrics._surface import _closest_on_triangles, _Surface

    a, b = _sphere(), _sphere(center=(0, 0, 0.3))
    r = metrics.chamfer(a, b, n_samples=20_000)
    np.testing.assert_allclose([r.accuracy, r.completeness], _offset_sphere_distance_mean(0.3), atol=MEAN_TOL)
    s = _Surface("b", b, 0, seed=0)
    q = metrics.sample_surface(a, 5000, seed=3)[0]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((s.v - s.center).astype(np.float32)), o3d.core.Tensor(s.f.astype(np.uint32)))
    fi = scene.compute_closest_points(o3d.core.Tensor((q - s.center).astype(np.float32)))["primitive_ids"].numpy()
    t = s.tri[fi.astype(np.int64)]
    embree = np.linalg.norm(_closest_on_triangles(q, t[:, 0], t[:, 1], t[:, 2]) - q, axis=1)
    # near-ties between faces are broken in float32 by each search: float64 distances agree to float32's resolution
    np.testing.assert_allclose(s.closest(q)[0], embree, atol=1e-6)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(4000, 3))
    rays = np.concatenate([np.zeros((4000, 3)) - s.center, d / np.linalg.norm(d, axis=1, keepdims=True)], axis=1)
    rays[::2, :3] += 3.0  # half start outside the sphere and mostly miss
    hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy().astype(np.float64)
    ours = s.cast(rays)
    assert np.isfinite(ours).sum() > 2000 and np.isinf(ours).sum() > 500  # both kinds of ray
    np.testing.assert_array_equal(np.isfinite(ours), np.isfinite(hit))
    np.testing.assert_allclose(ours[np.isfinite(ours)], hit[np.isfinite(hit)], rtol=1e-5, atol=1e-6)
