# SPDX-License-Identifier: Apache-2.0
"""Pure-torch reference for ``wtopo.ops.poisson_indicator`` (full complex FFT, index_add_ scatter)."""

import math

import torch

from .scatter_trilinear import sample_trilinear_ref, scatter_trilinear_ref


def poisson_indicator_ref(points, normals, weights, resolution, *, sigma, padding, level_sigma=0.0):
    """Return chi [R, R, R] following the documented DPSR recipe, written independently of the op."""
    r = resolution
    h = (1 + 2 * padding) / (r - 1)
    q = ((points + padding) / (r * h)).clamp(0.0, (r - 1) / r)
    v = scatter_trilinear_ref(q, weights[:, None] * normals, r)
    f = torch.fft.fftfreq(r, dtype=torch.float64, device=points.device)
    kx, ky, kz = torch.meshgrid(f, f, f, indexing="ij")
    k2 = (2 * math.pi) ** 2 * (kx ** 2 + ky ** 2 + kz ** 2)
    g = torch.exp(-0.5 * sigma ** 2 * k2)
    div = 0
    for axis, k in enumerate((kx, ky, kz)):
        kd = 2 * math.pi * k * (k.abs() != 0.5)  # a first derivative has no Nyquist mode
        div = div + 1j * kd.to(points.dtype) * torch.fft.fftn(v[..., axis])
    k2[0, 0, 0] = 1.0
    chi_h = -(g / k2).to(points.dtype) * div
    chi_h[0, 0, 0] = 0
    chi = torch.fft.ifftn(chi_h).real
    at = sample_trilinear_ref(chi[..., None], q)[:, 0]
    level = (weights * at).sum() / weights.sum() if weights.sum() > 1e-20 else chi.new_zeros(())
    if level_sigma > 0:  # the local level: blurred w chi(p) over blurred w, blended into the global level
        blur = torch.exp(-0.5 * level_sigma ** 2 * k2).to(points.dtype)
        blur[0, 0, 0] = 1.0  # k2 was set to 1 there above; the blur keeps sums
        num = torch.fft.ifftn(torch.fft.fftn(scatter_trilinear_ref(q, (weights * at)[:, None], r)[..., 0]) * blur).real
        den = torch.fft.ifftn(torch.fft.fftn(scatter_trilinear_ref(q, weights[:, None], r)[..., 0]) * blur).real
        den_at = sample_trilinear_ref(den[..., None], q)[:, 0]
        c = 0.05 * (weights * den_at).sum() / weights.sum() if weights.sum() > 1e-20 else 0.0
        level = torch.where(den + c > 0, (num + c * level) / (den + c), level)
    chi = chi - level
    scale = chi.abs().mean()
    return chi / scale if scale > 1e-10 else chi
