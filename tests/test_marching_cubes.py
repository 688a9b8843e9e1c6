# SPDX-License-Identifier: Apache-2.0
"""wtopo.ops.marching_cubes: skimage and torch references, per-configuration closedness, sphere
area and dA/dr, float64 gradchecks and the design/stability.md section 5 cases."""

import itertools
import math

import numpy as np
import pytest
import torch
from reference.marching_cubes import (
    ambiguous_cells,
    edge_report,
    edge_vertices,
    match_points,
    mesh_area,
    signed_volume,
    skimage_mesh,
    smooth_random_field,
    sphere_sdf,
)

from wtopo.marching_cubes import GRAD_EPS
from wtopo.ops import marching_cubes

# Vertex positions: both sides evaluate t = (level - a) / (b - a) on the same values; float64 leaves
# only rounding of the position arithmetic (~1e-16 relative), 1e-9 is far above that and far
# below the node spacing.  float32 (our kernels) vs float64 (skimage) differ by ~1e-7 * extent.
POS_TOL_F64 = 1e-9
POS_TOL_F32 = 2e-6
# skimage interpolates in float32 whatever the input dtype: measured 5e-8 on a unit box.
SKIMAGE_TOL = 1e-6
# Sphere area and dA/dr at 64^3 vs 4 pi r^2 and 8 pi r: marching cubes' discretisation error at
# r = 0.35 on a 1/63 grid measured -6.4e-4 (area) and -2.8e-5 (derivative), -5e-5 for the area at
# 256^3; the issue asks for 1e-2.
ANALYTIC_RTOL = 1e-2
# Gradients of the same vertices through our adjoint and torch autograd of the reference: both are
# exact formulas in float64, so only rounding separates them.
GRAD_RTOL, GRAD_ATOL = 1e-9, 1e-10


def check_mesh(verts: torch.Tensor, faces: torch.Tensor) -> None:
    """Output validation (STABILITY 5): shapes, dtypes, indices in range, no repeated vertex, finite."""
    assert verts.ndim == 2 and verts.shape[1] == 3
    assert faces.ndim == 2 and faces.shape[1] == 3 and faces.dtype == torch.int32
    assert bool(torch.isfinite(verts).all())
    if faces.shape[0]:
        assert int(faces.min()) >= 0 and int(faces.max()) < verts.shape[0]
        f = faces.long()
        assert bool(((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])).all())


def check_closed(verts: torch.Tensor, faces: torch.Tensor) -> None:
    """Every edge used by exactly two faces in opposite directions, and outward normals."""
    rep = edge_report(faces.cpu().numpy())
    assert set(rep["undirected_counts"]) == {2}, rep["undirected_counts"]
    assert rep["max_directed_repeat"] == 1
    assert signed_volume(verts.detach().cpu().double().numpy(), faces.cpu().numpy()) > 0


def test_sphere_matches_skimage_and_is_closed(device):
    """Give skimage's vertex set and face count on a sphere; closed, outward, right volume."""
    import trimesh

    r = 0.31
    f = sphere_sdf(40, r, center=(0.013, -0.021, 0.007))
    lower, upper = (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)
    verts, faces = marching_cubes(f.to(device), lower=lower, upper=upper)
    check_mesh(verts, faces)
    sv, sf = skimage_mesh(f.numpy(), 0.0, lower, upper)
    assert verts.shape[0] == sv.shape[0] and faces.shape[0] == sf.shape[0]
    idx, dist = match_points(verts.cpu().numpy(), sv)
    assert dist.max() < SKIMAGE_TOL and len(set(idx.tolist())) == len(idx)
    check_closed(verts, faces)
    mesh = trimesh.Trimesh(verts.cpu().numpy(), faces.cpu().numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    np.testing.assert_allclose(mesh.volume, 4 / 3 * math.pi * r**3, rtol=2e-2)


@pytest.mark.parametrize("seed,shape", [(0, (24, 24, 24)), (1, (20, 27, 17)), (2, (31, 9, 22))])
def test_random_smooth_fields_match_skimage(seed, shape):
    """Match skimage's vertices and face count on smooth random fields, anisotropic grids and bounds."""
    f = smooth_random_field(shape, seed, sigma=3.5)
    lower, upper = (-1.0, 0.5, 2.0), (0.7, 1.5, 2.2)
    verts, faces = marching_cubes(f, 0.1, lower=lower, upper=upper)
    check_mesh(verts, faces)
    sv, sf = skimage_mesh(f.numpy(), 0.1, lower, upper)
    assert faces.shape[0] > 0
    assert verts.shape[0] == sv.shape[0] and faces.shape[0] == sf.shape[0]
    _, dist = match_points(verts.numpy(), sv)
    assert dist.max() < SKIMAGE_TOL


@pytest.mark.parametrize("seed", [0, 5])
def test_rougher_fields_differ_from_skimage_only_in_ambiguous_cells(seed):
    """Keep every vertex of skimage's edge set; face counts differ at most within ambiguous cells."""
    f = smooth_random_field((24, 24, 24), seed, sigma=2.0)
    verts, faces = marching_cubes(f, 0.1)
    check_mesh(verts, faces)
    sv, sf = skimage_mesh(f.numpy(), 0.1)
    amb = ambiguous_cells(f.numpy(), 0.1)
    assert amb > 0  # the case this test is about
    _, dist = match_points(verts.numpy(), sv)
    assert dist.max() < SKIMAGE_TOL  # our vertices are all skimage's (it may add interior ones)
    assert 0 <= sv.shape[0] - verts.shape[0] <= amb
    assert abs(sf.shape[0] - faces.shape[0]) <= 4 * amb  # Lewiner tiles an ambiguous cell with <= 4 more


@pytest.mark.parametrize("dtype,tol", [(torch.float64, POS_TOL_F64), (torch.float32, POS_TOL_F32)])
def test_vertices_match_torch_reference(device, dtype, tol):
    """Give one vertex per crossed edge, at the reference's position, in float32 and float64."""
    f = smooth_random_field((18, 21, 16), 3, sigma=2.0)
    lower, upper = (0.0, -1.0, 0.25), (1.0, 1.0, 0.75)
    verts, faces = marching_cubes(f.to(device, dtype), -0.2, lower=lower, upper=upper)
    assert verts.dtype == dtype and verts.device.type == torch.device(device).type
    check_mesh(verts, faces)
    ref = edge_vertices(f, -0.2, lower, upper).numpy()
    assert verts.shape[0] == ref.shape[0]
    idx, dist = match_points(verts.cpu().double().numpy(), ref)
    assert dist.max() < tol and len(set(idx.tolist())) == len(idx)


@pytest.mark.parametrize("nz", [2, 16, 17, 18, 33, 34, 49])
def test_z_sizes_straddling_chunks(nz):
    """Match the reference for z sizes around the 16-node chunk boundaries (surface crossing them)."""
    from wtopo.marching_cubes import CHUNK

    assert CHUNK == 16  # the sizes above straddle multiples of it
    f = smooth_random_field((9, 7, nz), nz, sigma=1.5)
    verts, faces = marching_cubes(f, lower=(0, 0, 0), upper=(1, 1, 2))
    check_mesh(verts, faces)
    ref = edge_vertices(f, 0.0, (0, 0, 0), (1, 1, 2)).numpy()
    assert faces.shape[0] > 0 and verts.shape[0] == ref.shape[0]
    idx, dist = match_points(verts.numpy(), ref)
    assert dist.max() < POS_TOL_F64 and len(set(idx.tolist())) == len(idx)
    padded = torch.nn.functional.pad(f, (1,) * 6, value=10.0)
    check_closed(*marching_cubes(padded))


def test_vertex_gradient_matches_torch_reference(device):
    """Give the same field gradient as torch autograd of the reference for a random upstream."""
    f = smooth_random_field((14, 12, 15), 4, sigma=2.0)
    mine = f.clone().to(device).requires_grad_(True)
    verts, faces = marching_cubes(mine, lower=(0, 0, 0), upper=(1.3, 1.1, 1.4))
    assert faces.shape[0] > 0  # the gradient test exercised faces
    ref_f = f.clone().requires_grad_(True)
    ref = edge_vertices(ref_f, 0.0, (0, 0, 0), (1.3, 1.1, 1.4))
    idx, dist = match_points(verts.detach().cpu().numpy(), ref.detach().numpy())
    assert dist.max() < POS_TOL_F64
    g = torch.randn(verts.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (verts * g.to(device)).sum().backward()
    g_ref = torch.zeros_like(ref)
    g_ref[torch.as_tensor(idx)] = g
    (ref * g_ref).sum().backward()
    assert float(ref_f.grad.abs().sum()) > 0
    torch.testing.assert_close(mine.grad.cpu(), ref_f.grad, rtol=GRAD_RTOL, atol=GRAD_ATOL)


def test_gradcheck_float64(device):
    """Pass torch.autograd.gradcheck of the vertices w.r.t. the field on a 5x6x4 grid."""
    f = smooth_random_field((5, 6, 4), 5, sigma=1.0)
    f = torch.where(f.abs() < 0.05, torch.full_like(f, 0.05), f)  # keep nodes off the level: no topology flip
    f = f.to(device).requires_grad_(True)
    verts, faces = marching_cubes(f)
    assert faces.shape[0] > 0 and verts.shape[0] > 0
    assert not faces.requires_grad
    assert torch.autograd.gradcheck(lambda x: marching_cubes(x, lower=(-1, 0, 0), upper=(1, 2, 0.5))[0], (f,),
                                    eps=1e-6, atol=1e-6)


def _cube_patterns():
    """All 256 inside/outside patterns of one cell's 8 corners, as +-(0.3..1.3) values."""
    rng = np.random.default_rng(7)
    for code in range(256):
        vals = np.empty((2, 2, 2))
        for c, (i, j, k) in enumerate(itertools.product(range(2), repeat=3)):
            mag = 0.3 + rng.random()
            vals[i, j, k] = -mag if (code >> c) & 1 else mag
        yield code, vals


def test_every_cube_configuration_closed_and_outward():
    """Close every one of the 256 single-cell patterns (padded outside) with outward normals."""
    produced = 0
    for code, vals in _cube_patterns():
        f = np.pad(vals, 1, constant_values=1.0)  # outside shell: every inside region closes
        verts, faces = marching_cubes(torch.as_tensor(f), lower=(0, 0, 0), upper=(3, 3, 3))
        check_mesh(verts, faces)
        if code == 0:
            assert verts.shape[0] == 0 and faces.shape[0] == 0
            continue
        produced += 1
        check_closed(verts, faces)
        assert faces.shape[0] > 0
    assert produced == 255


def test_single_cell_faces_point_to_increasing_field():
    """Orient each unpadded 2^3 cell's faces towards the outside corners (normal . grad f > 0)."""
    for code, vals in _cube_patterns():
        verts, faces = marching_cubes(torch.as_tensor(vals))
        check_mesh(verts, faces)
        if code in (0, 255):
            assert faces.shape[0] == 0
            continue
        assert faces.shape[0] > 0
        v = verts.numpy()[faces.long().numpy()]
        normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        centroid = v.mean(axis=1)
        # trilinear interpolant's gradient at each face centroid
        x, y, z = centroid.T
        w = vals
        gx = ((w[1, 0, 0] - w[0, 0, 0]) * (1 - y) * (1 - z) + (w[1, 1, 0] - w[0, 1, 0]) * y * (1 - z)
              + (w[1, 0, 1] - w[0, 0, 1]) * (1 - y) * z + (w[1, 1, 1] - w[0, 1, 1]) * y * z)
        gy = ((w[0, 1, 0] - w[0, 0, 0]) * (1 - x) * (1 - z) + (w[1, 1, 0] - w[1, 0, 0]) * x * (1 - z)
              + (w[0, 1, 1] - w[0, 0, 1]) * (1 - x) * z + (w[1, 1, 1] - w[1, 0, 1]) * x * z)
        gz = ((w[0, 0, 1] - w[0, 0, 0]) * (1 - x) * (1 - y) + (w[1, 0, 1] - w[1, 0, 0]) * x * (1 - y)
              + (w[0, 1, 1] - w[0, 1, 0]) * (1 - x) * y + (w[1, 1, 1] - w[1, 1, 0]) * x * y)
        flux = (normals * np.stack([gx, gy, gz], 1)).sum(1)
        assert flux.sum() > 0, code


@pytest.mark.parametrize("seed", [0, 1])
def test_white_noise_is_crack_free(seed):
    """Close the mesh of white noise (every ambiguous case, padded outside): the table has no cracks."""
    rng = np.random.default_rng(seed)
    f = np.pad(rng.standard_normal((14, 15, 13)), 1, constant_values=1.0)
    verts, faces = marching_cubes(torch.as_tensor(f))
    check_mesh(verts, faces)
    assert faces.shape[0] > 100
    check_closed(verts, faces)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_node_values_equal_to_level(seed):
    """Produce no duplicate or zero-area faces when many nodes equal the level, and stay closed."""
    rng = np.random.default_rng(seed)
    f = np.pad(rng.integers(-1, 2, size=(12, 11, 13)).astype(np.float64), 1, constant_values=1.0)
    assert (f == 0).sum() > 100
    verts, faces = marching_cubes(torch.as_tensor(f))
    check_mesh(verts, faces)
    assert faces.shape[0] > 0
    v = verts.numpy()[faces.long().numpy()]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    assert area.min() > 1e-6
    keys = np.sort(faces.numpy(), axis=1)
    assert np.unique(keys, axis=0).shape[0] == keys.shape[0]
    assert np.unique(verts.numpy(), axis=0).shape[0] == verts.shape[0]  # no two vertices coincide
    rep = edge_report(faces.numpy())
    # Merged node vertices may pinch sheets together (an edge used by 4 or 6 faces), but the mesh
    # stays closed and consistently wound: every edge is traversed equally often both ways.
    assert all(n % 2 == 0 for n in rep["undirected_counts"]) and not rep["unbalanced_edges"]
    assert signed_volume(verts.numpy(), faces.numpy()) > 0


def test_plane_through_nodes_has_one_vertex_per_node(device):
    """Put one vertex on each node of a plane lying exactly on grid nodes, with its one-sided gradient."""
    n = 9
    z = torch.linspace(0, 1, n, dtype=torch.float64)
    f = (z - z[4]).expand(n, n, n).contiguous().to(device).requires_grad_(True)
    verts, faces = marching_cubes(f)
    check_mesh(verts, faces)
    assert verts.shape[0] == n * n and faces.shape[0] == 2 * (n - 1) ** 2
    torch.testing.assert_close(verts[:, 2].detach().cpu(), torch.full((n * n,), 0.5, dtype=torch.float64))
    verts[:, 2].sum().backward()
    # Each node vertex has one crossed edge (to the inside node below): raising the node's value
    # by d moves the plane down by d / (df/dz) = d, so d z / d f = -1 there and 0 elsewhere.
    expected = torch.zeros(n, n, n, dtype=torch.float64)
    expected[:, :, 4] = -1.0
    torch.testing.assert_close(f.grad.cpu(), expected)


@pytest.mark.parametrize("value", [1.0, -1.0, 0.0])
def test_field_without_crossing_is_empty(device, value):
    """Return [0, 3] outputs and a zero gradient for a field above, below or equal to the level."""
    f = torch.full((6, 5, 7), value, device=device, requires_grad=True)
    verts, faces = marching_cubes(f)
    assert verts.shape == (0, 3) and faces.shape == (0, 3) and faces.dtype == torch.int32
    assert verts.dtype == torch.float32
    verts.sum().backward()
    assert f.grad is not None and float(f.grad.abs().sum()) == 0.0


def test_nearly_equal_edge_values_clamp_gradient(device):
    """Keep forward and backward finite when an edge's values differ by 1e-7 (gradient clamped)."""
    f = sphere_sdf(6, 0.3, dtype=torch.float64)
    f[2, 2, 2], f[3, 2, 2] = -0.5e-7, 0.5e-7  # crossed x-edge with |b - a| = 1e-7
    f[2, 3, 2], f[2, 3, 3] = -1e-12, 1e-12  # |b - a| far below the guard
    f = f.to(device).requires_grad_(True)
    verts, faces = marching_cubes(f, lower=(-0.5,) * 3, upper=(0.5,) * 3)
    check_mesh(verts, faces)
    assert faces.shape[0] > 0
    verts.sum().backward()
    g = f.grad.cpu()
    assert bool(torch.isfinite(g).all())
    assert float(g.abs().max()) <= 2 * 0.2 / GRAD_EPS  # spacing / eps bounds each edge's term
    assert float(g[2, 3, 2].abs()) > 0


def test_surface_leaving_the_grid_is_open_on_the_boundary():
    """Keep the boundary cell layer: a sphere larger than the grid is cut open exactly on the boundary."""
    f = sphere_sdf(16, 0.55)  # grid is [-0.5, 0.5]^3: the sphere crosses every face of the box
    verts, faces = marching_cubes(f, lower=(-0.5,) * 3, upper=(0.5,) * 3)
    check_mesh(verts, faces)
    _, sf = skimage_mesh(f.numpy(), 0.0, (-0.5,) * 3, (0.5,) * 3)
    assert faces.shape[0] == sf.shape[0]
    rep = edge_report(faces.numpy())
    assert rep["boundary_edges"] and rep["max_directed_repeat"] == 1
    v = verts.numpy()
    for a, b in rep["boundary_edges"]:
        on_box = np.isclose(np.abs(v[[a, b]]), 0.5).all(axis=0)  # both ends on one face of the box
        assert on_box.any()
    padded = torch.nn.functional.pad(f, (1,) * 6, value=1.0)
    pv, pf = marching_cubes(padded, lower=(-0.5 - 1 / 15,) * 3, upper=(0.5 + 1 / 15,) * 3)
    check_closed(pv, pf)


@pytest.mark.parametrize("n", [2, 3, 8])
def test_small_grids(device, n):
    """Extract from 2^3, 3^3 and 8^3 grids (2^3 is the smallest valid grid)."""
    f = sphere_sdf(n, 0.45, center=(-0.3, -0.2, -0.25)).to(device).requires_grad_(True)
    verts, faces = marching_cubes(f, lower=(-0.5,) * 3, upper=(0.5,) * 3)
    check_mesh(verts, faces)
    assert faces.shape[0] > 0
    _, sf = skimage_mesh(f.detach().cpu().numpy(), 0.0)
    assert faces.shape[0] == sf.shape[0]
    verts.sum().backward()
    assert bool(torch.isfinite(f.grad).all())


def test_grid_256_forward():
    """Extract a sphere from a 256^3 float32 grid with a sane mesh."""
    f = sphere_sdf(256, 0.3, dtype=torch.float32)
    verts, faces = marching_cubes(f, lower=(-0.5,) * 3, upper=(0.5,) * 3)
    check_mesh(verts, faces)
    area = float(mesh_area(verts.double(), faces))
    np.testing.assert_allclose(area, 4 * math.pi * 0.3**2, rtol=ANALYTIC_RTOL)
    assert faces.shape[0] == 2 * verts.shape[0] - 4  # closed genus-0 surface: Euler characteristic 2


def test_sphere_area_and_radius_derivative():
    """Give area 4 pi r^2 and dA/dr 8 pi r for a sphere SDF at 64^3 (relative 1e-2)."""
    r = torch.tensor(0.35, dtype=torch.float64, requires_grad=True)
    f = sphere_sdf(64, r, center=(0.01, 0.02, -0.015))
    verts, faces = marching_cubes(f, lower=(-0.5,) * 3, upper=(0.5,) * 3)
    check_mesh(verts, faces)
    area = mesh_area(verts, faces)
    area.backward()
    np.testing.assert_allclose(float(area.detach()), 4 * math.pi * 0.35**2, rtol=ANALYTIC_RTOL)
    np.testing.assert_allclose(float(r.grad), 8 * math.pi * 0.35, rtol=ANALYTIC_RTOL)


def test_float32_and_float64_agree():
    """Give the same mesh in float32 and float64 up to float32 rounding."""
    f = smooth_random_field((20, 20, 20), 9, sigma=2.5)
    v64, f64 = marching_cubes(f)
    v32, f32 = marching_cubes(f.float())
    assert torch.equal(f64, f32)
    torch.testing.assert_close(v32.double(), v64, rtol=0, atol=POS_TOL_F32)


def test_repeated_backward_gives_same_gradient():
    """Return the same gradient when differentiated twice (the tape is zeroed in between)."""
    f = smooth_random_field((10, 10, 10), 11).requires_grad_(True)
    verts, faces = marching_cubes(f)
    assert faces.shape[0] > 0
    g1 = torch.autograd.grad(verts.square().sum(), f, retain_graph=True)[0]
    g2 = torch.autograd.grad(verts.square().sum(), f)[0]
    torch.testing.assert_close(g1, g2)


@pytest.mark.parametrize(
    "kwargs,exc,match",
    [
        ({"field": torch.zeros(4, 4)}, ValueError, "3 dimensions"),
        ({"field": torch.zeros(1, 4, 4)}, ValueError, "size >= 2"),
        ({"field": torch.zeros(4, 4, 4, dtype=torch.int32)}, TypeError, "dtype"),
        ({"field": np.zeros((4, 4, 4))}, TypeError, "torch.Tensor"),
        ({"field": torch.full((4, 4, 4), float("nan"))}, ValueError, "finite"),
        ({"level": float("inf")}, ValueError, "level must be finite"),
        ({"level": torch.tensor(0.0)}, TypeError, "level"),
        ({"lower": (0, 0)}, ValueError, "3 entries"),
        ({"upper": (1, 1, 0)}, ValueError, "upper must exceed lower"),
        ({"upper": (1, 1, float("nan"))}, ValueError, "upper must be finite"),
    ],
)
def test_invalid_arguments_raise(kwargs, exc, match):
    """Raise a typed error naming the argument before any launch."""
    args = {"field": torch.randn(4, 4, 4), "level": 0.0, "lower": (0, 0, 0), "upper": (1, 1, 1)}
    args.update(kwargs)
    field = args.pop("field")
    level = args.pop("level")
    with pytest.raises(exc, match=match):
        marching_cubes(field, level, **args)
