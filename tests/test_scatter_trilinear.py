# SPDX-License-Identifier: Apache-2.0
"""scatter_trilinear / sample_trilinear: reference, adjointness, gradchecks, boundary rule, determinism."""

import pytest
import torch
from reference.scatter_trilinear import sample_trilinear_ref, scatter_trilinear_ref

from wtopo.ops import sample_trilinear, scatter_trilinear

# float32: the op and index_add_ sum the same terms in a different order; a few ulps of O(10).
ATOL_F32 = 1e-4
# float64: summation-order differences only.
ATOL_F64 = 1e-11


def _tol(dtype):
    return ATOL_F32 if dtype == torch.float32 else ATOL_F64


def _assert_matches(out, ref, inputs, atol):
    """Compare values and the VJP for one random upstream gradient; the reference VJP must be non-zero."""
    torch.testing.assert_close(out, ref, atol=atol, rtol=0)
    up = torch.randn_like(ref)
    for a, b in zip(torch.autograd.grad(out, inputs, up), torch.autograd.grad(ref, inputs, up)):
        assert b.abs().sum() > 0
        torch.testing.assert_close(a, b, atol=atol * 10, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [1, 3, 6])  # 6 > 4 exercises the channel chunking
# 50_000 points exceeds the 16384-point threshold, so the CPU scatter runs slab-split across threads.
@pytest.mark.parametrize("n", [1, 257, 50_000])
def test_scatter_forward_and_vjp_match_reference(device, dtype, channels, n):
    """Match the index_add_ reference in value and VJP (points and values) for random upstream grads."""
    g = torch.Generator().manual_seed(n)
    p = torch.rand(n, 3, generator=g, dtype=dtype).to(device).requires_grad_()
    v = torch.randn(n, channels, generator=g, dtype=dtype).to(device).requires_grad_()
    _assert_matches(scatter_trilinear(p, v, 16), scatter_trilinear_ref(p, v, 16), (p, v), _tol(dtype))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_forward_and_vjp_match_reference(device, dtype):
    """Match the gather reference in value and VJP (grid and points)."""
    g = torch.Generator().manual_seed(3)
    grid = torch.randn(12, 12, 12, 5, generator=g, dtype=dtype).to(device).requires_grad_()  # 5 channels: chunked
    p = torch.rand(500, 3, generator=g, dtype=dtype).to(device).requires_grad_()
    _assert_matches(sample_trilinear(grid, p), sample_trilinear_ref(grid, p), (grid, p), _tol(dtype))


def test_gradcheck_float64(device):
    """Pass float64 gradcheck for scatter (points, values) and sample (grid, points) on an 8^3 grid."""
    g = torch.Generator().manual_seed(4)
    p = torch.rand(20, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    v = torch.randn(20, 2, generator=g, dtype=torch.float64).to(device).requires_grad_()
    grid = torch.randn(8, 8, 8, 2, generator=g, dtype=torch.float64).to(device).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: scatter_trilinear(a, b, 8), (p, v))
    assert torch.autograd.gradcheck(sample_trilinear, (grid, p))


def test_single_point_weights_are_analytic(device):
    """Put weights (1-f)/f products on the 8 surrounding nodes of a single point."""
    r = 4
    f = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)
    p = ((torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64) + f) / r).to(device)[None]
    grid = scatter_trilinear(p, torch.ones(1, 1, dtype=torch.float64, device=device), r)[..., 0].cpu()
    want = torch.zeros(r, r, r, dtype=torch.float64)
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                want[1 + di, 2 + dj, dk] = ((f[0] if di else 1 - f[0]) * (f[1] if dj else 1 - f[1])
                                            * (f[2] if dk else 1 - f[2]))
    torch.testing.assert_close(grid, want, atol=1e-15, rtol=0)
    assert grid.sum().item() == pytest.approx(1.0)


def test_last_cell_drops_the_missing_nodes(device):
    """Drop (never wrap) the share of the non-existent node R for a point in the last cell."""
    r = 4
    p = torch.tensor([[3.25 / r, 0.0, 0.0]], dtype=torch.float64, device=device)
    grid = scatter_trilinear(p, torch.ones(1, 1, dtype=torch.float64, device=device), r)[..., 0].cpu()
    assert grid[3, 0, 0].item() == pytest.approx(0.75)
    assert grid[0, 0, 0].item() == 0.0  # periodic wrap would have put 0.25 here
    assert grid.sum().item() == pytest.approx(0.75)


def test_scatter_and_sample_are_adjoint(device):
    """Satisfy <scatter(p, v), G> == <v, sample(G, p)>."""
    g = torch.Generator().manual_seed(5)
    p = torch.rand(300, 3, generator=g, dtype=torch.float64).to(device)
    v = torch.randn(300, 3, generator=g, dtype=torch.float64).to(device)
    grid = torch.randn(9, 9, 9, 3, generator=g, dtype=torch.float64).to(device)
    lhs = (scatter_trilinear(p, v, 9) * grid).sum()
    rhs = (v * sample_trilinear(grid, p)).sum()
    torch.testing.assert_close(lhs, rhs, atol=1e-10, rtol=1e-12)


@pytest.mark.parametrize("value", [1.0, -1e-7, 1.5, float("nan")])
def test_points_outside_domain_raise(device, value):
    """Raise ValueError naming the offending index and value for coordinates outside [0, 1)."""
    p = torch.full((5, 3), 0.5, device=device)
    p[3, 1] = value
    with pytest.raises(ValueError, match=r"points.*\[3, 1\]"):
        scatter_trilinear(p, torch.ones(5, 1, device=device), 8)
    with pytest.raises(ValueError, match=r"points.*\[3, 1\]"):
        sample_trilinear(torch.zeros(8, 8, 8, 1, device=device), p)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_values_raise(device, value):
    """Raise ValueError naming the index of a NaN/inf value."""
    v = torch.ones(5, 2, device=device)
    v[4, 1] = value
    with pytest.raises(ValueError, match=r"values.*\[4, 1\]"):
        scatter_trilinear(torch.full((5, 3), 0.5, device=device), v, 8)


@pytest.mark.parametrize("bad", ["resolution", "values_shape", "values_dtype", "grid_shape", "no_channels"])
def test_invalid_arguments_raise(device, bad):
    """Raise ValueError/TypeError naming the argument."""
    p = torch.rand(4, 3, device=device)
    if bad == "resolution":
        with pytest.raises(ValueError, match="resolution"):
            scatter_trilinear(p, torch.ones(4, 1, device=device), 1)
    elif bad == "values_shape":
        with pytest.raises(ValueError, match="values"):
            scatter_trilinear(p, torch.ones(3, 1, device=device), 8)
    elif bad == "no_channels":
        with pytest.raises(ValueError, match="values"):
            scatter_trilinear(p, torch.ones(4, 0, device=device), 8)
        with pytest.raises(ValueError, match="grid"):
            sample_trilinear(torch.zeros(8, 8, 8, 0, device=device), p)
    elif bad == "values_dtype":
        with pytest.raises(TypeError, match="values"):
            scatter_trilinear(p, torch.ones(4, 1, device=device, dtype=torch.float64), 8)
    else:
        with pytest.raises(ValueError, match="grid"):
            sample_trilinear(torch.zeros(8, 8, 7, 1, device=device), p)


def test_empty_point_set_gives_zero_grid(device):
    """Return a zero grid and zero-size gradients for N = 0."""
    p = torch.zeros(0, 3, device=device, requires_grad=True)
    v = torch.zeros(0, 3, device=device, requires_grad=True)
    grid = scatter_trilinear(p, v, 8)
    assert grid.shape == (8, 8, 8, 3) and (grid == 0).all()
    gp, gv = torch.autograd.grad(grid.sum(), (p, v))
    assert gp.shape == (0, 3) and gv.shape == (0, 3)
    assert sample_trilinear(torch.ones(8, 8, 8, 2, device=device), p).shape == (0, 2)


def test_all_points_in_one_voxel_finite(device):
    """Keep values and position gradients finite with every point in one voxel, at its corner included."""
    p = torch.full((1000, 3), 3.0 / 8, dtype=torch.float64, device=device)
    p[1:] += torch.rand(999, 3, dtype=torch.float64, device=device) * (0.999 / 8)
    p.requires_grad_()
    v = torch.ones(1000, 1, dtype=torch.float64, device=device, requires_grad=True)
    grid = scatter_trilinear(p, v, 8)
    assert grid.sum().item() == pytest.approx(1000.0)
    assert (grid[3:5, 3:5, 3:5] > 0).all()
    gp, gv = torch.autograd.grad((grid * torch.randn_like(grid)).sum(), (p, v))
    assert torch.isfinite(gp).all() and gp.abs().sum() > 0 and torch.isfinite(gv).all()


@pytest.mark.parametrize("layout", ["uniform", "skewed"])
def test_cpu_scatter_is_deterministic_across_thread_counts(monkeypatch, layout):
    """Give bitwise-identical grids for repeated runs and for 1 vs 2 CPU threads, matching the reference."""
    g = torch.Generator().manual_seed(6)
    p = torch.rand(100_000, 3, generator=g, dtype=torch.float64)
    if layout == "skewed":  # 90 % of the points in the first tenth of x: slabs must rebalance
        p[:90_000, 0] *= 0.1
    v = torch.randn(100_000, 3, generator=g, dtype=torch.float64)
    a = scatter_trilinear(p, v, 32)
    b = scatter_trilinear(p, v, 32)
    monkeypatch.setenv("WTOPO_NUM_THREADS", "1")
    c = scatter_trilinear(p, v, 32)
    assert torch.equal(a, b) and torch.equal(a, c)
    torch.testing.assert_close(a, scatter_trilinear_ref(p, v, 32), atol=ATOL_F64, rtol=0)
