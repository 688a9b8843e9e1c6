# SPDX-License-Identifier: Apache-2.0
"""Plane-sweep stereo initialisation (:mod:`wtopo.geometry.mvs`): analytic plane and sphere, a
distorted rig against its undistorted twin, untextured images, neighbour choice and the plan."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from lenses import barrel_twin

from wtopo import scenes
from wtopo.fitting._init_surfels import initial_surfels, spread_subset
from wtopo.fitting.config import FitConfig, InitConfig, InitSource
from wtopo.geometry.mvs import plane_sweep_points, select_neighbours


def _plane_scene(n_views=10):
    quad = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    return scenes.from_mesh(quad, n_views=n_views, resolution=(64, 48), rig="hemisphere", texture="astronaut",
                            background="black", seed=1)


def _footprint(scene) -> float:
    cam = scene.cameras[0]
    return float(np.linalg.norm(cam.center) / cam.K[0, 0])


@pytest.fixture(scope="module")
def plane():
    sc = _plane_scene()
    res = plane_sweep_points(sc.cameras, sc.images, np.array([-1.2, -1.2, -0.3]), np.array([1.2, 1.2, 0.3]), near=0.05)
    return sc, res


def test_plane_points_lie_on_the_plane_and_face_up(plane):
    sc, res = plane
    assert len(res.points) > 4000, "the sweep confirmed too few depths on a textured plane"
    px = _footprint(sc)
    err = np.abs(res.points[:, 2])
    # measured (10 views of 64 x 48 px, 40-degree baselines; the level-plane family warps the quad
    # exactly): median 0.11, 95th percentile 0.39 pixel footprints (camera-facing planes alone: 0.47 /
    # 1.5); a wrong projection or sweep puts them tens of footprints off
    assert np.median(err) < 0.3 * px and np.quantile(err, 0.95) < 1.0 * px
    # the 7-px window fattens the quad's edge into the black (depth-ambiguous) background: measured up to 7.7
    # of view 0's footprints (one point of 6,083; a grazing view's footprint is larger)
    assert np.all(np.abs(res.points[:, :2]) < 1.0 + 10 * px), "points far outside the textured quad"
    assert np.median(res.normals[:, 2]) > 0.99, "normals do not face the cameras above the plane"
    np.testing.assert_allclose(np.linalg.norm(res.normals, axis=1), 1.0, atol=1e-5)
    assert np.all((res.colors >= 0) & (res.colors <= 1))


@pytest.fixture(scope="module")
def sphere():
    ball = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    sc = scenes.from_mesh(ball, n_views=16, resolution=(64, 48), rig="sphere", texture="astronaut", seed=2)
    return sc, plane_sweep_points(sc.cameras, sc.images, np.full(3, -1.2), np.full(3, 1.2), near=0.05)


def _radial_error(points):
    return np.median(np.abs(np.linalg.norm(points, axis=1) - 1.0))


def test_sphere_points_lie_on_the_sphere(sphere):
    sc, res = sphere
    assert len(res.points) > 1000
    r = np.linalg.norm(res.points, axis=1)
    # the icosphere's facets sit up to 0.3 % inside the unit sphere; measured median |r - 1| 0.1 px
    assert _radial_error(res.points) < 0.4 * _footprint(sc)
    radial = np.sum(res.normals * res.points / r[:, None], axis=1)
    assert np.median(radial) > 0.85  # measured 0.91 (normals from 2-px depth differences)


def test_distorted_rig_matches_its_undistorted_twin(sphere):
    sc, twin = sphere
    cams, imgs = barrel_twin(sc)
    lo, hi = np.full(3, -1.2), np.full(3, 1.2)
    res = plane_sweep_points(cams, imgs, lo, hi, near=0.05)
    assert len(res.points) > 0.5 * len(twin.points)
    # measured median |r - 1|: 0.0154 against the twin's 0.0130 (the pinhole model on the distorted
    # images: 0.0202)
    assert _radial_error(res.points) < 1.35 * _radial_error(twin.points)


def test_untextured_images_give_no_points_and_init_falls_back():
    sc = _plane_scene(6)
    flat = torch.full_like(sc.images, 0.4)
    res = plane_sweep_points(sc.cameras, flat, np.full(3, -1.2), np.full(3, 1.2), near=0.05)
    assert len(res.points) == 0 and res.view_fraction == 0.0
    sc.images = flat
    norm = sc.normalized()
    with pytest.warns(RuntimeWarning, match="untextured"):
        s = initial_surfels(norm, InitConfig(num_points=300), InitSource.MVS, sh_degree=0, device=torch.device("cpu"),
                            generator=torch.Generator().manual_seed(0))
    assert len(s) == 300


def test_stereo_init_thins_evenly_and_orients_surfels(plane):
    sc, _ = plane
    norm = sc.normalized()
    s = initial_surfels(norm, InitConfig(num_points=500), InitSource.MVS, sh_degree=0, device=torch.device("cpu"),
                        generator=torch.Generator().manual_seed(0))
    assert 400 <= len(s) <= 500
    # normalisation only scales and shifts: the quad's normal is still the z axis
    nz = s.normals()[:, 2].abs()
    assert float(nz.median()) > 0.95, "stereo surfels are not oriented along the depth map's normal"
    pts = s.means.detach().numpy()
    # the points spread over the quad: no quarter of it is empty
    c = pts.mean(0)
    quarters = {(bool(x), bool(y)) for x, y in pts[:, :2] > c[:2]}
    assert len(quarters) == 4


def test_spread_subset_is_bounded_and_covers_clusters():
    rng = np.random.default_rng(0)
    dense = rng.normal(0, 0.01, (5000, 3))
    sparse = rng.uniform(1, 2, (200, 3))
    pts = np.concatenate([dense, sparse])
    pick = spread_subset(pts, 300, torch.Generator().manual_seed(0))
    assert len(pick) == 300 and len(np.unique(pick)) == 300
    assert (pick >= 5000).sum() > 100, "the sparse cluster lost out to the dense one"
    assert len(spread_subset(pts[:10], 300, torch.Generator())) == 10


def _spread_subset_by_unique(points, n, generator):
    """The definition, one ``np.unique`` of integer cells per grid: one random point per occupied cell of the
    coarsest power-of-two grid (up to 4096 per side) with at least ``n`` occupied cells."""
    if len(points) <= n:
        return np.arange(len(points))
    lo, span = points.min(0), float(np.ptp(points, axis=0).max()) or 1.0
    order = torch.randperm(len(points), generator=generator).numpy()
    cells = 2
    while True:
        _, first = np.unique(np.floor((points[order] - lo) / span * cells).astype(np.int64), axis=0, return_index=True)
        if len(first) >= n or cells >= 4096:
            break
        cells *= 2
    pick = order[np.sort(first)]
    if len(pick) > n:
        pick = pick[torch.randperm(len(pick), generator=generator).numpy()[:n]]
    return np.sort(pick)


@pytest.mark.parametrize("layout", ["uniform", "layers", "lattice", "duplicates", "span49", "lattice49"])
def test_spread_subset_matches_its_definition(layout, device):
    """On every device (CUDA divides by a host scalar through its reciprocal: 49 * (1 / 49) < 1 would move the
    farthest points, and a lattice on the finest cells' faces, a cell)."""
    rng = np.random.default_rng(3)
    pts = rng.random((20000, 3)) * np.array([4.0, 1.0, 0.3]) - 2.0
    if layout in ("span49", "lattice49"):  # the longest side exactly 49, its two extreme points on it
        pts = rng.random((20000, 3)) * np.array([49.0, 7.0, 3.0])
        pts[0, 0], pts[1, 0] = 0.0, 49.0
        if layout == "lattice49":
            pts = np.round(pts / 49 * 4096) * 49 / 4096
    if layout == "layers":  # a few planes: many empty cells
        pts[:, 2] = np.round(pts[:, 2] * 3) / 3
    elif layout == "lattice":  # points on cell faces of every grid
        pts = np.round(pts * 16) / 16
    elif layout == "duplicates":  # fewer distinct points than asked for
        pts = np.repeat(pts[:50], 400, axis=0)
    for n in (1, 37, 2000, 19999):
        got = spread_subset(pts, n, torch.Generator().manual_seed(n), device)
        want = _spread_subset_by_unique(pts, n, torch.Generator().manual_seed(n))
        assert np.array_equal(got, want), (layout, n)


def test_neighbours_on_an_orbit_are_the_adjacent_views():
    cams = scenes.rig_cameras("orbit", 24, np.zeros(3), 1.0, resolution=(32, 24))
    nb = select_neighbours(cams, np.zeros(3), k=4)
    for i, n in enumerate(nb):
        assert i not in n and len(n) == 4
        steps = sorted(min((j - i) % 24, (i - j) % 24) for j in n)
        assert steps == [1, 1, 2, 2], (i, n)
    fwd = scenes.rig_cameras("forward", 9, np.zeros(3), 1.0, resolution=(32, 24))
    assert all(len(n) == 4 for n in select_neighbours(fwd, np.zeros(3)))


def test_plan_picks_stereo_for_unmasked_scenes_only():
    from wtopo.fitting.plan import make_plan

    env = scenes.load("bunny_env", n_views=8, resolution=48, n_test=0)
    assert make_plan(env.normalized(), FitConfig(), torch.device("cpu")).init_source == "mvs"
    obj = scenes.load("bunny", n_views=8, resolution=48)
    assert make_plan(obj.normalized(), FitConfig(), torch.device("cpu")).init_source == "cameras"


def test_bad_arguments_are_named():
    sc = _plane_scene(4)
    with pytest.raises(ValueError, match="near"):
        plane_sweep_points(sc.cameras, sc.images, np.full(3, -1.0), np.full(3, 1.0), near=0.0)
    with pytest.raises(ValueError, match="at least 2 views"):
        plane_sweep_points(sc.cameras[:1], sc.images[:1], np.full(3, -1.0), np.full(3, 1.0), near=0.1)


def test_max_views_sweeps_an_even_subset(plane):
    sc, full = plane
    lo, hi = np.array([-1.2, -1.2, -0.3]), np.array([1.2, 1.2, 0.3])
    half = plane_sweep_points(sc.cameras, sc.images, lo, hi, near=0.05, max_views=5)
    assert 0 < len(half.points) < len(full.points)
    assert np.median(np.abs(half.points[:, 2])) < 0.3 * _footprint(sc)
    for bad in (1, 2.5, True):
        with pytest.raises(ValueError, match="max_views"):
            plane_sweep_points(sc.cameras, sc.images, lo, hi, near=0.05, max_views=bad)


def test_morton_code_interleaves_every_bit():
    """Bit b of axis a lands on bit 3 b + a, for every bit of 21-bit coordinates (the bit loop is the reference)."""
    from wtopo.fitting._init_surfels import _morton

    rng = np.random.default_rng(7)
    q = np.concatenate([rng.integers(0, 1 << 21, (500, 3)), [[0, 0, 0], [(1 << 21) - 1] * 3, [1, 0, 0], [0, 0, 1]]])
    want = np.zeros(len(q), np.int64)
    for b in range(21):
        for a in range(3):
            want |= ((q[:, a] >> b) & 1) << (3 * b + a)
    assert np.array_equal(_morton(torch.as_tensor(q)).numpy(), want)
