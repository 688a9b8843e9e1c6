# SPDX-License-Identifier: Apache-2.0
"""Loss terms of the fit, pure torch.

Every term is finite for any input the renderers produce: masks are applied before ``log`` (so
invalid pixels get exactly zero gradient), zero vectors are never normalised without an epsilon,
and a term over an empty mask is ``0`` (connected to the graph), never the NaN of an empty mean.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..metrics import ssim
from ..photometric import photometric_loss

__all__ = [
    "dilate",
    "erode",
    "masked_mean",
    "l1",
    "photometric",
    "mask_loss",
    "halo_target",
    "boundary_band",
    "depth_to_points",
    "depth_normals",
    "normal_consistency",
    "distortion",
    "scale_regularizer",
    "mesh_depth_loss",
    "mesh_normal_loss",
    "safe_normalize",
]

_NORMAL_EPS = 1e-8  # below this length a normal is treated as absent (zero alpha)
_SSIM_WINDOW = 11  # window of wtopo.metrics.ssim's defaults (smaller images take the torch path and its error)


def masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` over ``mask`` (same leading shape); ``0`` with the graph kept when empty."""
    m = mask.to(values.dtype)
    while m.ndim < values.ndim:
        m = m.unsqueeze(-1)
    m = m.expand_as(values)
    count = m.sum()
    return (values * m).sum() / count.clamp_min(1.0)


def safe_normalize(v: torch.Tensor, eps: float = _NORMAL_EPS) -> torch.Tensor:
    """``v / |v|`` over the last axis with ``|v|`` clamped to ``eps`` (zero stays zero, finite gradient)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference."""
    return (pred - target).abs().mean()


def photometric(pred: torch.Tensor, target: torch.Tensor, dssim: float) -> torch.Tensor:
    """``(1 - dssim) * L1 + dssim * (1 - SSIM)`` of images [H, W, 3] (SSIM of :func:`wtopo.metrics.ssim`).

    On CUDA the fused Warp loss :func:`wtopo.ops.photometric_loss` (four launches, equal up to
    float32 summation order); on CPU the torch formulation below (kept: the fits' CPU results stay
    bit for bit what they were).
    """
    if pred.is_cuda and min(pred.shape[0], pred.shape[1]) >= _SSIM_WINDOW:
        return photometric_loss(pred, target.detach().to(pred.dtype), dssim=dssim)
    loss = (1.0 - dssim) * l1(pred, target)
    if dssim > 0:
        loss = loss + dssim * (1.0 - ssim(pred, target))
    return loss


def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy between rendered opacity [H, W] and an object mask [H, W]: bool, or a
    float target opacity in [0, 1] (:func:`halo_target`)."""
    a = alpha.clamp(1e-6, 1 - 1e-6)  # BCE is infinite at exactly 0 / 1
    return F.binary_cross_entropy(a, mask.to(alpha.dtype))


def halo_target(mask: torch.Tensor, filter_sigma: float) -> torch.Tensor:
    """The opacity [H, W] (dtype float32, on ``mask``'s device) that splats whose centres lie exactly on
    the object's silhouette render, from a binary mask [H, W] bool sampled one ray per pixel.

    Inside the mask it is 1. Outside, the renderer's screen-space low-pass (a Gaussian of
    ``filter_sigma`` pixels around every projected centre) still covers the pixel: at a distance ``d``
    from the silhouette a line of opaque centres renders ``exp(-d^2 / (2 filter_sigma^2))``. The
    silhouette lies somewhere between the pixel's nearest inside pixel centre (Euclidean distance
    ``e``) and ``e - 1`` pixels from it, so the target is that opacity averaged over
    ``d`` uniform in ``[max(e - 1, 0), e]``: 0.44 on the first ring at ``filter_sigma = 0.35``, 0.10
    diagonally, below 0.003 from the second ring on; 0 everywhere for an empty mask. A binary target
    there instead makes the fit pull the centres about ``filter_sigma sqrt(2 ln 2)`` inside the
    silhouette to cancel the halo. Discrete (no gradient); computed on the CPU (SciPy's distance transform).
    """
    import math

    from scipy.ndimage import distance_transform_edt

    m = mask.detach().cpu().numpy().astype(bool)
    if not m.any():  # no object in this view: nothing to halo (the transform has no inside pixel to measure to)
        return torch.zeros(mask.shape, dtype=torch.float32, device=mask.device)
    e = torch.as_tensor(distance_transform_edt(~m), dtype=torch.float64)  # 0 inside, >= 1 outside
    lo, hi = (e - 1).clamp_min(0), e
    k = 1.0 / (math.sqrt(2.0) * float(filter_sigma))
    mean = (torch.erf(hi * k) - torch.erf(lo * k)) / (hi - lo).clamp_min(1e-12) * (math.sqrt(math.pi) / (2 * k))
    out = torch.where(torch.as_tensor(m), torch.ones_like(e), mean)
    return out.to(torch.float32).to(mask.device)


def dilate(mask: torch.Tensor, width: int) -> torch.Tensor:
    """Pixels [H, W] bool within ``width`` pixels (Chebyshev distance) of ``mask`` [H, W] bool: its
    dilation by a ``(2 width + 1)^2`` square; ``mask`` itself for ``width <= 0``. Not differentiable."""
    mask = mask.to(torch.bool)
    if width <= 0:
        return mask
    w = int(width)
    return F.max_pool2d(mask.to(torch.float32)[None, None], 2 * w + 1, 1, w)[0, 0] > 0


def erode(mask: torch.Tensor, width: int) -> torch.Tensor:
    """Pixels [H, W] bool of ``mask`` [H, W] bool whose ``(2 width + 1)^2`` square lies inside it (pixels
    beyond the image do not count against it); ``mask`` itself for ``width <= 0``. Not differentiable."""
    return ~dilate(~mask.to(torch.bool), width)


def boundary_band(mask: torch.Tensor, width: int) -> torch.Tensor:
    """Pixels [H, W] bool within ``width`` pixels (Chebyshev distance) of the boundary of ``mask`` [H, W]
    bool: the dilation minus the erosion by a ``(2 width + 1)^2`` square. Empty for ``width == 0``."""
    if width <= 0:
        return torch.zeros_like(mask, dtype=torch.bool)
    return dilate(mask, width) & ~erode(mask, width)


def depth_to_points(depth: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """World points [H, W, 3] of z-depths [H, W] along rays whose camera-z component is 1."""
    return origins + directions * depth[..., None]


def depth_normals(depth: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor,
                  valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals [H, W, 3] from a depth map by central differences, facing the camera, and their mask.

    Border pixels and pixels whose four neighbours are not all ``valid`` get a zero normal and
    ``False`` in the mask (2DGS pads borders with zero).
    """
    p = depth_to_points(torch.where(valid, depth, torch.zeros_like(depth)), origins, directions)
    dx = p[1:-1, 2:] - p[1:-1, :-2]
    dy = p[2:, 1:-1] - p[:-2, 1:-1]
    n = torch.cross(dx, dy, dim=-1)
    inner = valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1] & valid[1:-1, 1:-1]
    inner = inner & (n.norm(dim=-1) > _NORMAL_EPS)
    n = safe_normalize(n)
    # face the camera: the normal points against the viewing ray
    facing = (n * directions[1:-1, 1:-1]).sum(-1, keepdim=True)
    n = torch.where(facing > 0, -n, n)
    n = torch.where(inner[..., None], n, torch.zeros_like(n))
    out = F.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
    mask = F.pad(inner, (1, 1, 1, 1), value=False)
    return out, mask


def normal_consistency(rendered: torch.Tensor, from_depth: torch.Tensor, alpha: torch.Tensor,
                       mask: torch.Tensor) -> torch.Tensor:
    """Alpha-weighted ``1 - <n_rendered, n_depth>`` over ``mask`` (2DGS).

    ``rendered`` [H, W, 3] is the alpha-weighted rendered normal (its length is about the alpha), so
    ``<rendered, n_depth>`` is weighted by coverage without normalising zero vectors.
    """
    dot = (rendered * from_depth.detach()).sum(-1)
    return masked_mean(alpha.detach() - dot, mask)


def distortion(dist: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of the rendered depth-distortion map [H, W] (over ``mask`` when given)."""
    return dist.mean() if mask is None else masked_mean(dist, mask)


def scale_regularizer(scales: torch.Tensor, max_anisotropy: float) -> torch.Tensor:
    """Scale regulariser of linear scales [N, 2] or [N, 3].

    With three scales: the shortest axis (PGSR's flattening of 3D Gaussians). With two (2D
    surfels, flat by construction): ``relu(max / min - max_anisotropy)``, which stops needles.
    Zero surfels give 0.
    """
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    if scales.shape[-1] == 3:
        return scales.min(dim=-1).values.mean()
    ratio = scales.max(dim=-1).values / scales.min(dim=-1).values.clamp_min(1e-12)
    return F.relu(ratio - max_anisotropy).mean()


def mesh_depth_loss(surfel_depth: torch.Tensor, mesh_depth: torch.Tensor, mask: torch.Tensor, *,
                    eps: float, form: str = "log_ratio", extent: float = 1.0, debias: bool = False,
                    robust: float = 0.0, robust_behind: bool = False, behind: float = 1.0) -> torch.Tensor:
    """Agreement of surfel depth and proxy-mesh depth [H, W] on ``mask`` (pixels both cover).

    ``form="log_ratio"``: ``|log d_s - log d_m|``; ``"log1p_abs"``: ``log1p(|d_m - d_s| / extent)``.
    Depths are masked before the ``log`` and clamped to ``eps`` (scene units), so invalid pixels
    have exactly zero gradient. Empty mask -> 0.

    ``debias=True`` subtracts the median over ``mask`` of the difference (``log d_s - log d_m``, or
    ``d_s - d_m``) before the absolute value: a constant offset between the two surfaces in this
    view (the Poisson proxy's smoothing puts it inside the surfels on convex objects) carries no
    loss, and moving every pixel by the same amount gets no gradient; only the difference of their
    shapes does. The median is part of the loss (its gradient reaches the median pixel) and is taken
    without a host read (``nanmedian`` over the masked pixels; 0 when there are none).

    ``robust > 0`` (scene units) makes the penalty Cauchy-like, ``s * log1p(|diff| / s)`` with ``s``
    the depth ``robust`` in the form's units (``robust / d_m`` per pixel for the log ratio,
    ``robust / extent`` for ``log1p_abs``): about ``|diff|`` where the surfaces agree within
    ``robust``, its pull halved at ``robust`` and falling as ``1 / |diff|`` beyond, so pixels where the
    proxy is far off (a thin part the Poisson smoothing swelled) pull little. ``log1p_abs`` with
    ``robust == extent`` is the plain form. Differentiable in both depths (``s`` included).

    ``robust_behind=True`` keeps the Cauchy form to the pixels where the surfels lie behind the proxy
    (``diff > 0``: the proxy pulls them towards the camera, as over a thin part it swelled) and gives the
    pixels in front the plain penalty (floaters and bumps are pulled back in full). Both sides meet
    continuously at ``diff = 0``.
    """
    ds = torch.where(mask, surfel_depth, torch.ones_like(surfel_depth)).clamp_min(eps)
    dm = torch.where(mask, mesh_depth, torch.ones_like(mesh_depth)).clamp_min(eps)
    if form == "log_ratio":
        diff = torch.log(ds) - torch.log(dm)
    elif form == "log1p_abs":
        diff = (ds - dm) / extent
    else:
        raise ValueError(f"form must be 'log_ratio' or 'log1p_abs', got {form!r}")
    if debias:
        # pixels off the mask are left out of the median as NaN; their shifted value is masked out below
        diff = diff - torch.nan_to_num(torch.nanmedian(torch.where(mask, diff, torch.full_like(diff, float("nan")))))
    err = diff.abs() if form == "log_ratio" else torch.log1p(diff.abs())
    if robust > 0:
        s = robust / dm if form == "log_ratio" else robust / extent
        cauchy = s * torch.log1p(diff.abs() / s)
        err = torch.where(diff > 0, cauchy, err) if robust_behind else cauchy
    if behind != 1.0:
        err = torch.where(diff > 0, behind * err, err)
    return masked_mean(err, mask)


def mesh_normal_loss(surfel_normal: torch.Tensor, mesh_normal: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``1 - |<n_surfel, n_mesh>|`` on ``mask``, both [H, W, 3].

    The rendered normal is normalised safely; the absolute value makes the term independent of
    the proxy mesh's orientation (a face seen from behind agrees as well). Empty mask -> 0.
    """
    ns = safe_normalize(torch.where(mask[..., None], surfel_normal, torch.zeros_like(surfel_normal)))
    nm = torch.where(mask[..., None], mesh_normal, torch.zeros_like(mesh_normal))
    dot = (ns * nm).sum(-1).abs()
    return masked_mean(1.0 - dot, mask)
