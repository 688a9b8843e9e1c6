# SPDX-License-Identifier: Apache-2.0
"""Differentiable spectral Poisson surface reconstruction (DPSR) from weighted oriented points.

Pipeline: Warp trilinear scatter of ``weight * normal`` onto a periodic grid that covers the unit
cube plus ``padding`` on every side -> ``torch.fft.rfftn`` -> solve ``laplacian(chi) = div(V)``
with an optional Gaussian low-pass -> ``irfftn`` -> Warp trilinear sample of ``chi`` at the points
to shift the zero level onto them -> normalise. Every step is differentiable (Warp explicit
adjoints for scatter/sample, torch autograd for the FFTs).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from typing import NamedTuple

import torch

from ._profile import section
from ._validate import require_int_range, require_positive, require_same_device, require_tensor, value_checks
from .scatter import check_finite, check_unit_points, sample_unchecked, scatter_unchecked

__all__ = ["PoissonField", "PoissonContext", "poisson_indicator"]

# chi is divided by mean |chi| only where that exceeds NORM_FLOOR. For any non-degenerate point set
# mean |chi| is orders of magnitude above 1e-10 (it scales like the total weight / R^2); for an
# empty set or all weights zero chi is exactly 0 and is returned as is, never divided by ~0.
NORM_FLOOR = 1e-10
# The level (weighted mean of chi at the points) is 0 when the total weight is below this. 1e-20
# keeps 1 / total weight, and hence every gradient, finite in float32.
WEIGHT_FLOOR = 1e-20
# A local level (``level_sigma > 0``) blends into the global one where the blurred point weight falls
# under this share of its weighted mean at the points (about 2.5 sigma away from every point).
LEVEL_BLEND = 0.05


def _safe_divide(num: torch.Tensor, den: torch.Tensor, floor: float) -> torch.Tensor:
    """``num / den`` where ``den > floor``, else ``num``; finite gradients either way (double ``where``)."""
    ok = den > floor
    return num / torch.where(ok, den, torch.ones_like(den))


class PoissonField(NamedTuple):
    """Result of :func:`poisson_indicator`.

    Attributes:
        chi: indicator field, shape ``[R, R, R]``, dtype of the points; negative inside, 0 at the
            points (weighted mean), positive outside, scaled so that its mean absolute value is 1
            (all 0 for an empty point set or all-zero weights).
        lower: position (in the points' frame) of node ``(0, 0, 0)``: ``(-padding,) * 3``.
        upper: position of node ``(R-1, R-1, R-1)``: ``(1 + padding,) * 3``.
    """

    chi: torch.Tensor
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]


class PoissonContext:
    """Cache of the spectral operators of :func:`poisson_indicator`, keyed by resolution, sigma, device, dtype.

    Building the frequency grids and the Gaussian-filtered inverse Laplacian costs about as much
    as an FFT; a fit loop that calls :func:`poisson_indicator` every iteration reuses them. A
    module-level context is used when none is passed. Thread-safe; keeps the ``max_entries`` most
    recently used operators.

    Args:
        max_entries: number of cached operators (one is ``R^2 (R/2+1)`` floats plus 3 vectors).
    """

    def __init__(self, max_entries: int = 4):
        self.max_entries = require_int_range("max_entries", max_entries, 1)
        self._cache: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def operator(self, resolution: int, sigma: float, device: torch.device, dtype: torch.dtype):
        """Return ``(wx [R,1,1], wy [1,R,1], wz [1,1,R//2+1], S [R,R,R//2+1])`` for ``rfftn`` spectra.

        ``w*`` are angular frequencies in radians per voxel with the Nyquist entry zeroed (a first
        derivative has no real-valued Nyquist mode); ``S = G / |w|^2`` with the Gaussian
        ``G = exp(-|w|^2 sigma^2 / 2)`` (``sigma`` in voxels) and ``S = 0`` at the DC term.
        """

        def inverse_laplacian(w2: torch.Tensor) -> torch.Tensor:
            s = torch.exp(-0.5 * sigma ** 2 * w2) / torch.where(w2 > 0, w2, torch.ones_like(w2))
            return torch.where(w2 > 0, s, torch.zeros_like(s))  # the DC term (w2 = 0 there alone)

        def build():
            r = resolution
            w, wr = _frequencies(r)
            wd, wrd = w.clone(), wr.clone()
            if r % 2 == 0:
                wd[r // 2] = 0.0
                wrd[-1] = 0.0
            return (wd.view(r, 1, 1).to(device, dtype), wd.view(1, r, 1).to(device, dtype),
                    wrd.view(1, 1, -1).to(device, dtype), _spectrum(r, inverse_laplacian, device, dtype))

        return self._cached((resolution, float(sigma), str(device), dtype), build)

    def blur(self, resolution: int, sigma: float, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """The Gaussian ``exp(-|w|^2 sigma^2 / 2)`` [R, R, R//2+1] on the ``rfftn`` spectrum (``sigma`` in voxels):
        a periodic Gaussian blur of standard deviation ``sigma`` voxels, its DC term 1 (it keeps sums)."""
        return self._cached(("blur", resolution, float(sigma), str(device), dtype),
                            lambda: _spectrum(resolution, lambda w2: torch.exp(-0.5 * sigma ** 2 * w2), device, dtype))

    def _cached(self, key, build):
        """The cached value of ``key``, built by ``build()`` (outside the lock) on a miss."""
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        value = build()
        with self._lock:
            self._cache[key] = value
            while len(self._cache) > self.max_entries:
                self._cache.popitem(last=False)
        return value


def _frequencies(r: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(w [R], wr [R//2+1])``: the angular frequencies (radians per voxel) of ``fftn`` and ``rfftn``
    spectra, float64 on the CPU."""
    w = 2 * math.pi * torch.fft.fftfreq(r, dtype=torch.float64)
    wr = 2 * math.pi * torch.fft.rfftfreq(r, dtype=torch.float64)
    return w, wr


def _spectrum(r: int, fn, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``fn(|w|^2)`` [R, R, R//2+1] on ``device`` in ``dtype`` for an ``rfftn`` spectrum: ``fn`` maps float64
    squared angular frequencies elementwise, evaluated one ``[R, R//2+1]`` slab at a time, so the float64
    work costs a slab, not three grids (at 768^3 those were 5.4 GB beside the solve's own)."""
    w, wr = _frequencies(r)
    y2, z2 = w[:, None] ** 2, wr[None, :] ** 2
    out = torch.empty((r, r, wr.numel()), dtype=dtype)
    for i in range(r):
        out[i] = fn(w[i] ** 2 + y2 + z2).to(dtype)
    return out.to(device)


_DEFAULT_CONTEXT = PoissonContext()


def _solve(chi_h: torch.Tensor, s: torch.Tensor, r: int) -> torch.Tensor:
    """``irfftn(-i s chi_h)`` in place on ``chi_h`` (the spectrum of ``w . V``): chi [R, R, R]."""
    chi_h *= s
    chi_h *= -1j
    return torch.fft.irfftn(chi_h, s=(r, r, r), dim=(0, 1, 2))


class _SpectralSolve(torch.autograd.Function):
    """chi [R, R, R] of ``laplacian(chi) = div(V)`` for a vector grid V [R, R, R, 3] on the ``rfftn`` spectrum.

    Forward: ``chi^ = -i s (wx V^x + wy V^y + wz V^z)``. The map is a real convolution with an odd kernel,
    so its adjoint is the same solve with ``+i``: the backward is one ``rfftn`` of the incoming gradient and
    one batched ``irfftn`` (autograd's backward of ``rfftn`` runs a full complex transform of all three
    components). Equal to autograd's gradient to float64 round-off (``tests/test_poisson.py``).
    """

    @staticmethod
    def forward(ctx, v, wx, wy, wz, s):
        r = v.shape[0]
        vh = torch.fft.rfftn(v.permute(3, 0, 1, 2), dim=(1, 2, 3))
        chi_h = wx * vh[0]
        chi_h += wy * vh[1]
        chi_h += wz * vh[2]
        del vh
        ctx.save_for_backward(wx, wy, wz, s)
        return _solve(chi_h, s, r)

    @staticmethod
    def backward(ctx, grad):
        wx, wy, wz, s = ctx.saved_tensors
        r = grad.shape[0]
        gh = torch.fft.rfftn(grad)
        gh *= s
        gh *= 1j
        spec = torch.stack([gh * wx, gh * wy, gh * wz])
        del gh
        gv = torch.fft.irfftn(spec, s=(r, r, r), dim=(1, 2, 3)).permute(1, 2, 3, 0)
        return gv, None, None, None, None


def poisson_indicator(points: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor, resolution: int, *,
                      sigma: float = 1.0, padding: float = 0.1, level_sigma: float = 0.0,
                      context: PoissonContext | None = None) -> PoissonField:
    """Solve for the indicator function of weighted oriented points with an FFT Poisson solve (DPSR).

    The grid has ``R`` nodes per axis spanning ``[-padding, 1 + padding]`` (node spacing
    ``h = (1 + 2 padding) / (R - 1)``) and is periodic with period ``R h``: the last node is one
    voxel away from the first across the wrap, so ``padding`` (unit-cube units) is what keeps a
    surface near one face from leaking into the opposite one. ``V = sum_n w_n n_n delta(x - p_n)``
    is splatted trilinearly (normals are used as given: a zero normal contributes nothing),
    ``laplacian(chi) = div(V)`` is solved spectrally with the DC term zeroed and a Gaussian of
    standard deviation ``sigma`` **voxels** applied to ``V`` (``sigma = 0``: no smoothing). chi is
    then shifted so that its weight-averaged value at the points is 0 and divided by its mean
    absolute value (left as is when that is below ``1e-10``, i.e. for a zero field): outward
    normals give chi < 0 inside.

    One level for all points suits a closed surface, where chi takes one value on it. An open sheet
    (a ground the region of interest cuts) takes another: chi is antisymmetric across it, so the
    level of a closed part beside it moves the sheet's zero crossing off the sheet and closes it over
    its unseen side. ``level_sigma > 0`` shifts chi by a *local* level instead: the weight-averaged
    value of chi at the points under a Gaussian of ``level_sigma`` voxels,
    ``L(x) = (G * sum w chi(p) delta_p + c L0) / (G * sum w delta_p + c)`` with ``L0`` the global level and
    ``c`` = :data:`LEVEL_BLEND` times the blurred weight's weighted mean at the points, so ``L`` is the
    global level farther than about 2.5 ``level_sigma`` from every point.

    Args:
        points: positions, shape ``[N, 3]``, float32 or float64, in ``[0, 1]^3`` (anything in the
            padded box ``[-padding, 1 + padding]^3`` is accepted; outside or NaN raises
            :class:`ValueError`).
        normals: outward normals, shape ``[N, 3]``, dtype of ``points``; need not be unit length;
            NaN/inf raise :class:`ValueError`.
        weights: non-negative weights, shape ``[N]``, dtype of ``points``.
        resolution: ``R >= 4`` nodes per axis; any integer (powers of two are fastest).
        sigma: Gaussian smoothing standard deviation in grid voxels, ``>= 0``.
        padding: margin around the unit cube in unit-cube units, ``>= 0``; 0.1 (as SAP) is safe for
            geometry filling the unit cube.
        level_sigma: standard deviation in voxels of the local level's Gaussian, ``>= 0``; 0 (the
            default) shifts by one global level. Two more trilinear scatters and FFT pairs.
        context: operator cache (see :class:`PoissonContext`); a shared module-level one by default.

    Returns:
        :class:`PoissonField` ``(chi [R, R, R], lower, upper)``, so that
        ``marching_cubes(f.chi, lower=f.lower, upper=f.upper)`` yields vertices in the points'
        frame. ``chi`` is differentiable w.r.t. ``points`` (trilinear weights: C0 across cells),
        ``normals`` and ``weights``. An empty point set or all-zero weights give ``chi = 0``.
        Validation costs one host sync.

    References:
        Peng et al., "Shape As Points: A Differentiable Poisson Solver", NeurIPS 2021.

    Limitations:
        Periodic boundary: geometry closer than about ``2 sigma + 1`` voxels to the padded box
        boundary interacts with the opposite side.
    """
    require_tensor("points", points, shape=(None, 3))
    n = points.shape[0]
    dtype = points.dtype
    require_tensor("normals", normals, shape=(n, 3), dtypes=(dtype,))
    require_tensor("weights", weights, shape=(n,), dtypes=(dtype,))
    device = require_same_device(points=points, normals=normals, weights=weights)
    require_int_range("resolution", resolution, 4)
    sigma = require_positive("sigma", sigma, allow_zero=True)
    padding = require_positive("padding", padding, allow_zero=True)
    level_sigma = require_positive("level_sigma", level_sigma, allow_zero=True)
    if value_checks():  # host syncs: validation only (points are clamped into the grid below either way)
        check_unit_points("points", points, -padding, 1.0 + padding, closed=True)
        check_finite("normals", normals)
        check_finite("weights", weights)
        neg = (weights.detach() < 0).nonzero()
        if neg.numel():
            i = int(neg[0])
            raise ValueError(f"weights must be >= 0, got {weights[i].item()} at index {i}")

    r = resolution
    period = (1.0 + 2.0 * padding) * r / (r - 1)
    # Grid coordinates in [0, (R-1)/R]: never in the wrap cell, so the scatter drops nothing.
    q = ((points + padding) / period).clamp(0.0, (r - 1) / r)
    ctx = context or _DEFAULT_CONTEXT
    wx, wy, wz, s = ctx.operator(r, sigma, device, dtype)
    values = weights[:, None] * normals
    # laplacian(chi) = div(V)  <=>  -|w|^2 chi^ = i w . V^  <=>  chi^ = -i (w . V^) / |w|^2, summed in place
    # (the same operations in the same order; the products' backward keeps the operators, not their outputs)
    if torch.is_grad_enabled() and (points.requires_grad or normals.requires_grad or weights.requires_grad):
        with section("scatter"):
            v = scatter_unchecked(q, values, r)
        chi = _SpectralSolve.apply(v, wx, wy, wz, s)
        del v  # the solve keeps no grid for its backward: at 768^3 one is 5.4 GB
    else:  # nothing to differentiate (the final re-mesh): one component at a time, a third of the memory
        chi_h = None
        for c, wc in enumerate((wx, wy, wz)):
            with section("scatter"):
                vc = scatter_unchecked(q, values[:, c:c + 1].contiguous(), r)[..., 0]
            term = torch.fft.rfftn(vc)
            del vc
            term *= wc
            chi_h = term if chi_h is None else chi_h.add_(term)
            del term
        chi = _solve(chi_h, s, r)
        del chi_h
    at_points = sample_unchecked(chi[..., None], q)[:, 0]
    wsum = weights.sum()
    level = _safe_divide((weights * at_points).sum(), wsum, WEIGHT_FLOOR) * (wsum > WEIGHT_FLOOR)
    if level_sigma > 0:
        level = _local_level(q, weights, at_points, level, ctx.blur(r, level_sigma, device, dtype), wsum)
    chi = chi - level
    chi = _safe_divide(chi, chi.abs().mean(), NORM_FLOOR)
    lo, hi = -padding, 1.0 + padding
    return PoissonField(chi, (lo, lo, lo), (hi, hi, hi))


def _local_level(q: torch.Tensor, weights: torch.Tensor, at_points: torch.Tensor, level: torch.Tensor,
                 blur: torch.Tensor, wsum: torch.Tensor) -> torch.Tensor:
    """The local level field [R, R, R] of :func:`poisson_indicator` (``level_sigma > 0``): the blurred
    ``w chi(p)`` over the blurred ``w``, blended into the global ``level`` where the blurred weight is small."""
    r = blur.shape[0]
    with section("scatter"):
        src = scatter_unchecked(q, torch.stack([weights * at_points, weights], dim=1), r)
    sh = torch.fft.rfftn(src.permute(3, 0, 1, 2), dim=(1, 2, 3)) * blur
    num, den = torch.fft.irfftn(sh, s=(r, r, r), dim=(1, 2, 3))
    den_at = sample_unchecked(den[..., None], q)[:, 0]
    c = LEVEL_BLEND * _safe_divide((weights * den_at).sum(), wsum, WEIGHT_FLOOR) * (wsum > WEIGHT_FLOOR)
    # den + c > 0 wherever any weight is (the blur's float ringing is far below c); an empty set: the
    # global level (0), never 0 / 0
    ok = (den + c) > 0
    return torch.where(ok, (num + c * level) / torch.where(ok, den + c, torch.ones_like(den)), level)
