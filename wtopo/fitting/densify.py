# SPDX-License-Identifier: Apache-2.0
"""Density control: screen-space clone/split, opacity prune and reset, and the mesh-guided steps.

The mesh-guided steps use nearest-face queries on the proxy mesh's BVH
(:meth:`wtopo.raycast.MeshRaycaster.closest_faces`):

* geometry-aware prune: surfels far from the mesh AND of low opacity go;
* geometry-aware densification: faces that are no surfel's nearest face spawn a surfel;
* normal sign alignment: the sign of each surfel's normal fed to the Poisson solve (the TSDF
  scaffold triangle's, else a nearby proxy face's, else the cameras' side).

Every step keeps the optimiser state aligned (:class:`wtopo.fitting.surfels.Surfels`), never removes
all surfels and respects a hard cap on the count.
"""

from __future__ import annotations

import math

import torch

from .config import NormalFlip
from .surfels import Surfels, normals_to_quats

__all__ = [
    "accumulate_gradients",
    "accumulate_view_directions",
    "clone_and_split",
    "prune_by_opacity",
    "reset_opacity",
    "geometry_prune",
    "geometry_densify",
    "align_normal_signs",
    "face_normals",
    "MIN_SURFELS",
]

MIN_SURFELS = 16
"""Prunes never leave fewer surfels than this (a zero-size backward is never entered)."""
GRAD_THRESHOLD = 5e-4
"""Mean screen-space gradient norm (NDC units) above which a surfel is cloned or split (3DGS: 2e-4)."""
PERCENT_DENSE = 0.01
"""Surfels larger than this fraction of the scene extent are split, smaller ones cloned (3DGS's value)."""
MAX_GROWTH = 0.5
"""One clone/split step adds at most this fraction of the current count (largest gradients first)."""


def accumulate_gradients(surfels: Surfels, means2d_grad: torch.Tensor, visible: torch.Tensor,
                         width: int, height: int) -> None:
    """Add the screen-space gradient norm (NDC units, as 3DGS) of visible surfels to the accumulators.

    Args:
        surfels: the surfels whose ``grad_accum`` and ``grad_count`` buffers are updated in place.
        means2d_grad: gradient of the loss w.r.t. the projected centres [N, 2] in pixels.
        visible: [N] bool, surfels that touched at least one pixel.
        width: image width in pixels, to convert the gradient to NDC units.
        height: image height in pixels, to convert the gradient to NDC units.
    """
    g = means2d_grad.detach()
    norm = torch.hypot(g[:, 0] * (0.5 * width), g[:, 1] * (0.5 * height))  # scalar factors: no host-to-device copy
    surfels.buffers["grad_accum"] += torch.where(visible, norm, 0.0)
    surfels.buffers["grad_count"] += visible


def accumulate_view_directions(surfels: Surfels, camera_center: torch.Tensor, visible: torch.Tensor) -> None:
    """Add the unit direction from each visible surfel towards the camera centre [3]."""
    d = camera_center.to(surfels.means) - surfels.means.detach()
    weight = visible[:, None] / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # 1 / |d| where visible, else 0
    surfels.buffers["view_dirs"].addcmul_(d, weight)


def _keep_at_least(keep: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
    need = min(MIN_SURFELS, keep.numel())
    if int(keep.sum()) >= need:
        return keep
    keep = keep.clone()
    keep[torch.topk(score, need).indices] = True
    return keep


def prune_by_opacity(surfels: Surfels, threshold: float, *, max_scale: float | None = None) -> int:
    """Remove surfels with opacity below ``threshold`` (and larger than ``max_scale`` when given)."""
    op = surfels.opacities.detach()
    keep = op >= threshold
    if max_scale is not None:
        keep &= surfels.scales.detach().max(dim=-1).values <= max_scale
    keep = _keep_at_least(keep, op)
    removed = int((~keep).sum())
    if removed:
        surfels.prune(keep)
    return removed


def clone_and_split(surfels: Surfels, extent: float, max_surfels: int, generator: torch.Generator | None = None, *,
                    grad_threshold: float | None = None, percent_dense: float | None = None,
                    max_growth: float | None = None) -> tuple[int, int]:
    """3DGS densification: surfels with a mean screen-space gradient above ``grad_threshold`` are cloned
    (small) or split (large, scale > ``percent_dense * extent``). The count never exceeds
    ``max_surfels`` and grows by at most ``max_growth`` per call: the largest gradients go first.
    ``None``: :data:`GRAD_THRESHOLD`, :data:`PERCENT_DENSE`, :data:`MAX_GROWTH`. Resets the accumulators.
    Returns (cloned, split)."""
    grad_threshold = GRAD_THRESHOLD if grad_threshold is None else grad_threshold
    percent_dense = PERCENT_DENSE if percent_dense is None else percent_dense
    max_growth = MAX_GROWTH if max_growth is None else max_growth
    b = surfels.buffers
    mean_grad = b["grad_accum"] / b["grad_count"].clamp_min(1.0)
    big = surfels.scales.detach().max(dim=-1).values > percent_dense * extent
    cand = mean_grad >= grad_threshold
    room = max(0, min(max_surfels - len(surfels), int(max_growth * len(surfels))))
    if int(cand.sum()) > room:
        score = torch.where(cand, mean_grad, torch.full_like(mean_grad, -1.0))
        sel = torch.zeros_like(cand)
        if room:
            sel[torch.topk(score, room).indices] = True
        cand = cand & sel
    clone_mask = cand & ~big
    split_mask = cand & big
    n_clone = surfels.clone(clone_mask)
    # the clones were appended at the end: extend the split mask with False for them
    split_mask = torch.cat([split_mask, torch.zeros(n_clone, dtype=torch.bool, device=split_mask.device)])
    n_split = surfels.split(split_mask, generator=generator)
    b = surfels.buffers
    b["grad_accum"].zero_()
    b["grad_count"].zero_()
    return n_clone, n_split


def reset_opacity(surfels: Surfels, value: float) -> None:
    """Clamp every opacity to at most ``value`` and zero its Adam moments (3DGS opacity reset)."""
    logit = math.log(value / (1 - value))
    surfels.set_param("opacity_logits", surfels.params["opacity_logits"].detach().clamp(max=logit))


def face_normals(verts: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit face normals [F, 3] (winding order) and face areas [F] of a mesh."""
    v = verts.detach()
    f = faces.long()
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    c = torch.cross(e1, e2, dim=-1)
    area = 0.5 * c.norm(dim=-1)
    return c / c.norm(dim=-1, keepdim=True).clamp_min(1e-20), area


def geometry_prune(surfels: Surfels, distance: torch.Tensor, *, max_distance: float, max_opacity: float) -> int:
    """Remove surfels farther than ``max_distance`` from the mesh AND with opacity below ``max_opacity``.

    ``distance`` [N] is each surfel's distance to the proxy mesh (inf where none was found).
    """
    op = surfels.opacities.detach()
    keep = ~((distance > max_distance) & (op < max_opacity))
    keep = _keep_at_least(keep, op)
    removed = int((~keep).sum())
    if removed:
        surfels.prune(keep)
    return removed


def geometry_densify(surfels: Surfels, verts: torch.Tensor, faces: torch.Tensor, nearest_face: torch.Tensor, *,
                     max_new: int, max_surfels: int, opacity: float = 0.1,
                     generator: torch.Generator | None = None) -> int:
    """Spawn one surfel on each proxy face that is no surfel's nearest face.

    The new surfel sits at the face centroid, its normal is the face normal, its scale comes from
    the face area and its colour from the surfel nearest to the centroid. At most ``max_new``
    (randomly chosen, largest-area first when capped) and never beyond ``max_surfels``.
    """
    nf = faces.shape[0]
    if nf == 0 or len(surfels) == 0:
        return 0
    covered = torch.zeros(nf, dtype=torch.bool, device=faces.device)
    ok = nearest_face >= 0
    covered[nearest_face[ok].long()] = True
    idx = torch.nonzero(~covered).flatten()
    budget = min(max_new, max(0, max_surfels - len(surfels)))
    if idx.numel() == 0 or budget == 0:
        return 0
    normals, area = face_normals(verts, faces)
    if idx.numel() > budget:
        idx = idx[torch.topk(area[idx], budget).indices]
    f = faces[idx].long()
    v = verts.detach().float()
    centroid = v[f].mean(dim=1)
    tangent = v[f[:, 1]] - v[f[:, 0]]
    scale = torch.sqrt(area[idx].float().clamp_min(1e-12)) * 0.5
    # colour of the nearest existing surfel (exact, chunked to bound memory)
    means = surfels.means.detach()
    nearest = torch.empty(idx.numel(), dtype=torch.long, device=means.device)
    for s in range(0, idx.numel(), 1024):
        nearest[s:s + 1024] = torch.cdist(centroid[s:s + 1024], means).argmin(dim=1)
    p, b = surfels.take(nearest)
    logit = math.log(opacity / (1 - opacity))
    new = {
        "means": centroid,
        "quats": normals_to_quats(normals[idx].float(), tangent),
        "log_scales": torch.log(scale)[:, None].expand(-1, 2).clone(),
        "opacity_logits": torch.full((idx.numel(),), logit, device=means.device),
        "sh_dc": p["sh_dc"],
        "sh_rest": p["sh_rest"],
    }
    b["normal_sign"] = torch.ones(idx.numel(), device=means.device)
    b["mesh_sign"] = torch.ones(idx.numel(), device=means.device)  # the face normal's side
    surfels.append(new, b)
    return int(idx.numel())


def align_normal_signs(surfels: Surfels, mode: NormalFlip, *, mesh_normal: torch.Tensor | None = None,
                       distance: torch.Tensor | None = None, distance_scales: float = 0.0,
                       min_agreement: float = 0.5, generator: torch.Generator | None = None) -> dict[str, int]:
    """Choose each surfel's normal sign for the Poisson solve (``buffers["normal_sign"]``).

    ``mesh`` (mesh-guided signs): a surfel whose sign came from a mesh triangle when it was made
    (``buffers["mesh_sign"]``: the TSDF scaffold's, whose orientation comes from a signed distance
    field, or the proxy face it was spawned on) keeps it. Any other surfel takes its nearest proxy
    face's side where that face is closer than ``distance_scales`` times the surfel's larger in-plane
    scale and its normal agrees with the surfel's axis (``|cos| >= min_agreement``), and otherwise
    the side of the accumulated directions towards the cameras that saw it (surfels never seen keep
    their sign). The proxy does not override a scaffold sign: at a coarse grid the nearest face of a
    surfel on one side of a thin part can be the other side's (on the hard suite's ``chair_ground``
    that flipped 619 scaffold surfels and moved the proxy from 2.0 % to 6.8 % of the diagonal off
    the truth). Without ``mesh_normal`` / ``distance`` (no proxy) the face rule is skipped.
    ``view``: the camera side for every seen surfel (ablation). ``random``: a random sign (ablation).

    Args:
        surfels: ``buffers["normal_sign"]`` is updated in place.
        mode: the rule.
        mesh_normal: unit normal [N, 3] of each surfel's nearest proxy face (any value where none).
        distance: distance [N] to that face (``inf`` where none was found).
        distance_scales: the face is near when closer than this many in-plane sigmas of the surfel.
        min_agreement: least ``|cos|`` between the surfel's axis and the face normal.
        generator: seeds ``random``.

    Returns:
        How many surfels each rule decided (``mesh``: a near face, ``kept``: a triangle's sign, ``view``).
    """
    n = surfels.normals()
    b = surfels.buffers
    sign = b["normal_sign"].clone()
    if mode == NormalFlip.RANDOM:
        r = torch.randint(0, 2, (len(surfels),), generator=generator, device="cpu").to(n.device)
        b["normal_sign"] = (r * 2 - 1).float()
        return {"random": len(surfels)}
    vd = b["view_dirs"]
    view_sign = torch.where((n * vd).sum(-1) >= 0, 1.0, -1.0)
    seen = vd.norm(dim=-1) > 0
    if mode == NormalFlip.VIEW:
        b["normal_sign"] = torch.where(seen, view_sign, sign).float()
        return {"view": int(seen.sum())}
    fixed = b["mesh_sign"] > 0
    use = torch.zeros_like(seen)
    if mesh_normal is not None and distance is not None:
        mdot = (n * mesh_normal).sum(-1)
        size = surfels.scales.detach().max(dim=-1).values
        use = (distance < distance_scales * size) & (mdot.abs() >= min_agreement) & ~fixed
        sign = torch.where(use, torch.where(mdot >= 0, 1.0, -1.0), sign)
    view = seen & ~use & ~fixed
    b["normal_sign"] = torch.where(view, view_sign, sign).float()
    return {"mesh": int(use.sum()), "kept": int(fixed.sum()), "view": int(view.sum())}
