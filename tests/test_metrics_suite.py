# SPDX-License-Identifier: Apache-2.0
"""Floaters and holes (wtopo.metrics.floaters / holes) on analytic cases, and the flat albedo of
wtopo.scenes.from_mesh that the hard-scene suite (lab/hard.py) renders its untextured object with."""

import math

import numpy as np
import pytest
import trimesh

from wtopo import metrics, scenes

N = 100_000  # samples: binomial std of an area fraction near 0.25 is 1.4e-3


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=1.0)


def _without_cap(mesh, z):
    """The mesh without its faces whose centroid lies above ``z``, and the removed area."""
    keep = mesh.triangles_center[:, 2] <= z
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out, float(mesh.area_faces[~keep].sum())


def _with_box(mesh, side, center):
    box = trimesh.creation.box(extents=(side, side, side))
    box.apply_translation(center)
    return trimesh.util.concatenate([mesh, box])


def test_sphere_without_cap_has_the_cap_as_hole(sphere):
    pred, removed = _without_cap(sphere, 0.5)
    tau = 1e-3
    h = metrics.holes(pred, sphere, tau, n_samples=N)
    # every removed point is farther than tau from pred except a band of width tau along the rim
    rim = 2 * math.pi * math.sqrt(1 - 0.5 ** 2)
    assert removed - rim * tau - 0.01 * removed <= h.area <= removed + 0.01 * removed
    assert h.area == pytest.approx(math.pi, rel=0.03)  # the cap z > 0.5 of the unit sphere: 2 pi (1 - 0.5)
    assert h.area_fraction == pytest.approx(removed / sphere.area, abs=0.006)
    assert h.tau == tau
    # the hole is the f-score's missing recall, sample for sample
    assert h.area_fraction == pytest.approx(1 - metrics.f_score(pred, sphere, tau, n_samples=N).recall, abs=1e-12)
    # the cap is no floater: what pred has, the truth has
    fl = metrics.floaters(pred, sphere, tau, n_samples=N)
    assert fl.area_fraction == 0 and fl.count == 0 and fl.components == 1


def test_a_wide_tau_closes_the_hole(sphere):
    pred, _ = _without_cap(sphere, 0.9)  # a cap of height 0.1: every point within 0.45 of the rim
    assert metrics.holes(pred, sphere, 0.5, n_samples=N).area_fraction == 0.0
    assert metrics.holes(pred, sphere, 1e-3, n_samples=N).area_fraction > 0.01


def test_detached_cube_is_one_floater_of_its_area(sphere):
    pred = _with_box(sphere, 0.2, (3.0, 0.0, 0.0))
    tau = 0.01
    fl = metrics.floaters(pred, sphere, tau, n_samples=N)
    assert fl.components == 2
    assert fl.count == 1
    assert fl.count_area == pytest.approx(6 * 0.2 ** 2, rel=1e-9)
    assert fl.area == pytest.approx(0.24, rel=0.06)
    assert fl.area_fraction == pytest.approx(0.24 / (sphere.area + 0.24), abs=0.0015)
    assert fl.area_fraction == pytest.approx(1 - metrics.f_score(pred, sphere, tau, n_samples=N).precision,
                                             abs=1e-12)
    assert metrics.holes(pred, sphere, tau, n_samples=N).area_fraction == 0.0


def test_a_cube_touching_the_truth_is_far_area_but_no_floater(sphere):
    # the cube spans x in [0.95, 1.15]: it cuts the sphere, most of its area is farther than tau
    fl = metrics.floaters(_with_box(sphere, 0.2, (1.05, 0.0, 0.0)), sphere, 0.01, n_samples=N)
    assert fl.components == 2 and fl.count == 0 and fl.count_area == 0.0
    assert 0.005 < fl.area_fraction < 0.24 / sphere.area


def test_a_floater_below_the_sample_spacing_is_still_counted(sphere):
    # 6e-4 of area: about 5 of the 100k samples land on it, fewer than 1 with 1,000 samples
    pred = _with_box(sphere, 0.01, (0.0, 0.0, 2.0))
    fl = metrics.floaters(pred, sphere, 0.01, n_samples=1000)
    assert fl.count == 1 and fl.count_area == pytest.approx(6e-4, rel=1e-9)


def test_empty_and_bad_arguments(sphere):
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert metrics.holes(empty, sphere, 0.01).area_fraction == 1.0
    assert metrics.holes(empty, sphere, 0.01).area == pytest.approx(sphere.area)
    fl = metrics.floaters(empty, sphere, 0.01)
    assert (fl.count, fl.components, fl.area_fraction) == (0, 0, 0.0)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="tau"):
            metrics.floaters(sphere, sphere, bad)
        with pytest.raises(ValueError, match="tau"):
            metrics.holes(sphere, sphere, bad)
    with pytest.raises(ValueError, match="n_samples"):
        metrics.holes(sphere, sphere, 0.01, n_samples=0)


def test_mesh_stats_components_unchanged(sphere):
    two = _with_box(sphere, 0.2, (3.0, 0.0, 0.0))
    assert metrics.mesh_stats(two)["n_components"] == 2
    assert metrics.mesh_stats(sphere)["n_components"] == 1


def test_flat_texture_shows_only_shading():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sc = scenes.from_mesh(mesh, texture="flat", n_views=3, resolution=32)
    img, m = sc.images.numpy(), sc.masks.numpy()
    fg = img[m]
    assert len(fg) > 100
    assert np.allclose(fg[:, 0], fg[:, 1]) and np.allclose(fg[:, 1], fg[:, 2])  # grey: no colour, no texture
    # albedo 0.7 times Lambertian shading in [ambient 0.3, 1.1]: varies with the normal only
    assert fg.min() >= 0.7 * 0.3 - 1e-6 and fg.max() <= 0.7 * 1.1 + 1e-6
    assert fg.max() - fg.min() > 0.2
    tex = scenes.from_mesh(mesh, texture="astronaut", n_views=3, resolution=32)
    assert tex.images.numpy()[tex.masks.numpy()].std(axis=0).mean() > fg.std(axis=0).mean()
    with pytest.raises(ValueError, match="flat"):
        scenes.from_mesh(mesh, texture="plain", n_views=1, resolution=8)
