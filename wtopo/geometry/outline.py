# SPDX-License-Identifier: Apache-2.0
"""A mesh's outline against the training masks: how far its silhouettes lie inside (or outside) them.

A fit of Gaussian surfels renders each surfel through a screen-space low-pass, so near a limb the surfels'
silhouette reaches a fraction of a pixel past the surface they sit on; the mask and photometric terms then
hold the surface that much inside the object (design/decisions.md, "Kept: the outline offset"). The final
mesh has no low-pass: ray cast from a training view, its silhouette should cover that view's mask.
:func:`outline_offset` measures by how much it falls short, in pixels per view and as one distance, and
:func:`offset_along_normals` moves a mesh by it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

__all__ = ["OutlineOffset", "offset_along_normals", "outline_offset"]

_MIN_PIXELS = 64  # a view whose mask or silhouette covers fewer pixels says nothing about the outline
# the mask's pixel edges (4-neighbour changes) over-count a curve's length by 4/pi on average over its directions
_EDGE_LENGTH = np.pi / 4


@dataclass(frozen=True)
class OutlineOffset:
    """What :func:`outline_offset` measured.

    Attributes:
        pixels: each used view's offset, in pixels (float64 [U]): + where the silhouette lies inside the mask (the
            mesh should grow), - outside.
        footprints: each used view's pixel footprint at its silhouette's outline, ``z / fx`` in the cameras' units
            (float64 [U]).
        views: the indices of the used views (int64 [U]), in ``cameras``' order.
    """

    pixels: np.ndarray
    footprints: np.ndarray
    views: np.ndarray

    @property
    def distance(self) -> float:
        """The median over the used views of each view's offset times its footprint, in the cameras' units (0 when
        no view was used)."""
        return float(np.median(self.pixels * self.footprints)) if len(self.pixels) else 0.0

    @property
    def median_pixels(self) -> float:
        """The median of :attr:`pixels` (0 when no view was used)."""
        return float(np.median(self.pixels)) if len(self.pixels) else 0.0

    def capped(self, max_pixels: float) -> float:
        """:attr:`distance` limited to ``max_pixels`` times the median footprint (0 when no view was used)."""
        if not len(self.footprints):
            return 0.0
        limit = float(max_pixels) * float(np.median(self.footprints))
        return float(np.clip(self.distance, -limit, limit))


def _mask_array(i: int, mask, camera) -> np.ndarray:
    m = mask.detach().cpu().numpy() if torch.is_tensor(mask) else np.asarray(mask)
    if m.shape != (camera.height, camera.width):
        raise ValueError(f"masks[{i}] must have its camera's shape ({camera.height}, {camera.width}), got {m.shape}")
    if m.dtype != bool and not np.all(np.isfinite(m)):
        raise ValueError(f"masks[{i}] must be finite, got {int(np.sum(~np.isfinite(m)))} non-finite values")
    return m >= 0.5


def outline_offset(verts, faces, cameras: Sequence, masks: Sequence, *, device: torch.device | str = "cpu",
                   raycaster=None) -> OutlineOffset:
    """How far the silhouettes of a mesh lie inside the masks, per view and as one distance.

    Per view: ``(mask area - silhouette area) / the mask outline's length``, in pixels (the silhouette is the
    mesh ray cast through each pixel centre, the mask thresholded at 0.5), times the pixel footprint at the
    median depth of the silhouette's outline pixels (``z / fx``: the limb, where the offset is). Views whose mask
    touches the image border (the object is cut off: its outline there is the frame's) or whose mask or silhouette
    covers fewer than 64 pixels are left out.

    Args:
        verts: mesh vertices [V, 3] (NumPy or torch, the cameras' frame and units).
        faces: triangles [F, 3] (integer).
        cameras: :class:`wtopo.Camera` per view.
        masks: one mask per camera, [H, W] (bool or float, >= 0.5 inside), its camera's size.
        device: where the ray cast runs.
        raycaster: a :class:`wtopo.raycast.MeshRaycaster` to cast with (``None``: a new one): one that cast this
            mesh's faces before only refits its BVH to moved vertices.

    Returns:
        :class:`OutlineOffset` (``distance`` 0 and no views when none could be used). Not differentiable.

    Raises:
        ValueError: ``cameras`` and ``masks`` differ in length, a mask's shape is not its camera's, a mask or a
            vertex is not finite.
    """
    from ..raycast import MeshRaycaster

    if len(cameras) != len(masks):
        raise ValueError(f"masks must have one entry per camera ({len(cameras)}), got {len(masks)}")
    arrays = [_mask_array(i, m, c) for i, (m, c) in enumerate(zip(masks, cameras))]
    v = torch.as_tensor(np.ascontiguousarray(verts.detach().cpu() if torch.is_tensor(verts) else verts),
                        dtype=torch.float32)
    f = torch.as_tensor(np.ascontiguousarray(faces.cpu() if torch.is_tensor(faces) else faces), dtype=torch.int32)
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"verts must be finite, got {int((~torch.isfinite(v)).any(dim=-1).sum())} non-finite rows")
    v, f = v.to(device), f.to(device)
    caster = MeshRaycaster() if raycaster is None else raycaster  # one BVH for every view
    pix, feet, used = [], [], []
    for i, (cam, mk) in enumerate(zip(cameras, arrays)):
        if mk.sum() < _MIN_PIXELS or mk[0].any() or mk[-1].any() or mk[:, 0].any() or mk[:, -1].any():
            continue
        with torch.no_grad():
            r = caster.raycast(v, f, cam)
        hit = r.mask.cpu().numpy().astype(bool)
        if hit.sum() < _MIN_PIXELS:
            continue
        length = float((mk[1:] != mk[:-1]).sum() + (mk[:, 1:] != mk[:, :-1]).sum()) * _EDGE_LENGTH
        px = float(mk.sum() - hit.sum()) / length
        inner = hit.copy()  # the silhouette's own pixels: a hit whose four neighbours are all hits is not one
        inner[1:-1, 1:-1] &= hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
        z = r.depth.cpu().numpy()[hit & ~inner]
        z = float(np.median(z)) if len(z) else float("nan")
        if not (np.isfinite(px) and np.isfinite(z) and z > 0):
            continue  # no outline pixel (the silhouette fills the frame) or a degenerate hit
        pix.append(px)
        feet.append(z / float(cam.K[0, 0]))
        used.append(i)
    return OutlineOffset(np.asarray(pix, dtype=np.float64), np.asarray(feet, dtype=np.float64),
                         np.asarray(used, dtype=np.int64))


def offset_along_normals(mesh: trimesh.Trimesh, distance: float) -> trimesh.Trimesh:
    """A copy of ``mesh`` (its faces and vertex colours kept) with every vertex moved along its vertex normal.

    Args:
        mesh: the mesh; its vertex normals (trimesh's, area-weighted) point outward for a closed, outward-wound mesh.
        distance: how far, in the mesh's units: + along the normals (grows an outward-wound mesh), - against them.

    Returns:
        The moved copy (``mesh`` itself is not changed). Not differentiable.
    """
    out = mesh.copy()
    if len(mesh.faces) and distance != 0.0:
        out.vertices = np.asarray(mesh.vertices, dtype=np.float64) + mesh.vertex_normals * float(distance)
    return out
