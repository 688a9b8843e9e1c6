# SPDX-License-Identifier: Apache-2.0
"""A mesh's outline against the training masks: how far its silhouettes lie inside (or outside) them.

A fit of Gaussian surfels renders each surfel through a screen-space low-pass, so near a limb the surfels'
silhouette reaches a fraction of a pixel past the surface they sit on; the mask and photometric terms then
hold the surface that much inside the object (design/decisions.md, "Kept: the outline offset"). The final
mesh has no low-pass: ray cast from a training view, its silhouette should cover that view's mask.
:func:`outline_offset` measures by how much it falls short, in pixels per view and as one distance, and
:func:`offset_along_normals` moves a mesh by it.

The measure counts only the outline that smooth limbs draw. A fit also rounds a boxy object's sharp edges, and such
an object's silhouettes are drawn largely by its edges: there the silhouette falls short of the mask because the
edge is rounded, not because the surface lies inside, and moving every face out by it moves the faces away from
the truth (a chair: 0.0938 -> 0.1090 % Chamfer, design/decisions.md). :func:`ridge_spread` tells the two apart
from the mesh: a limb whose surface bends within a few pixels is an edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from ..camera import Camera

__all__ = ["OutlineOffset", "offset_along_normals", "outline_offset", "ridge_spread"]

_MIN_PIXELS = 64  # a view whose mask or silhouette covers fewer pixels says nothing about the outline
# the mask's pixel edges (4-neighbour changes) over-count a curve's length by 4/pi on average over its directions
_EDGE_LENGTH = np.pi / 4
# the ridge test: ridge_spread's grid cell, in the views' median pixel footprint (a box 4.5 footprints across) ...
RIDGE_CELL_PIXELS = 1.5
# ... and the spread above which a limb's face is an edge: a sphere reads below it when its radius exceeds about
# 9 footprints, a rounded right-angled edge reads about 0.29
RIDGE_SPREAD = 0.02
# a view is measured when at least this many of its outline pixels lie on smooth limbs
MIN_SMOOTH_PIXELS = 32
# ... and an edge's spread in that box is more than this share of its spread in cells twice as large: a smooth surface
# bends about a quarter as much in the finer box (the spread grows with the box's size squared), an edge as much
RIDGE_GROWTH = 0.5
_REACH_PIXELS = 8.0  # how far (in footprints) the ridge test looks past an outline pixel's hit, along its face's plane
_REACH_STEPS = 4  # in steps of 2 footprints: the finer ridge box reaches 1.5 cells (2.25 footprints) each way


@dataclass(frozen=True)
class OutlineOffset:
    """What :func:`outline_offset` measured.

    Attributes:
        pixels: each used view's offset along its smooth limbs, in pixels (float64 [U]): + where the silhouette lies
            inside the mask (the mesh should grow), - outside.
        footprints: each used view's pixel footprint at its silhouette's outline, ``z / fx`` in the cameras' units
            (float64 [U]).
        views: the indices of the used views (int64 [U]), in ``cameras``' order.
        shares: each measurable view's share of outline pixels on smooth limbs (float64 [M]); the used views are
            those of them with at least :data:`MIN_SMOOTH_PIXELS` such pixels.
    """

    pixels: np.ndarray
    footprints: np.ndarray
    views: np.ndarray
    shares: np.ndarray

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


def ridge_spread(verts, faces, points, cell: float) -> np.ndarray:
    """How much a mesh bends around each of ``points``: 1 - |the sum of the surface's area-weighted normals| / its
    area, over the 27 cells of a grid of side ``cell`` around the point's own cell.

    The surface is sampled by area, a few samples a cell (each face at least its centre), so that faces larger than
    a cell count where their area is.

    Args:
        verts: vertices [V, 3] (float, NumPy).
        faces: triangles [F, 3] (integer, NumPy).
        points: where to evaluate [P, 3] (float, NumPy), e.g. points on the mesh.
        cell: the grid's cell side, in the vertices' units (> 0; at least 2^-20 of the mesh's extent).

    Returns:
        float64 [P] in [0, 1]: 0 on a plane, about ``(box half-width / radius)^2 / 3`` on a sphere, up to 0.29 near a
        right-angled edge however it is rounded within the box (1 - cos 45 degrees, where both sides weigh the same),
        0.42 at a box's corner, NaN where the box holds no area. Not differentiable.

    Raises:
        ValueError: ``cell`` is not a positive finite distance.
    """
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive distance, got {cell}")
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    q = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(f) == 0 or len(q) == 0:
        return np.full(len(q), np.nan)
    tri = v[f]
    n = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # area-weighted normals
    area = np.linalg.norm(n, axis=1)
    lo = np.minimum(tri.min(axis=(0, 1)), q.min(axis=0))
    cell = max(float(cell), float(np.ptp(np.concatenate([tri.reshape(-1, 3), q]), axis=0).max()) / 2**20)
    # samples: the centre, and for a face wider than half a cell a few more a cell, at fixed barycentric points
    k = np.minimum(np.ceil(4.0 * area / cell**2), 4096).astype(np.int64)
    k[k < 1] = 1
    face = np.repeat(np.arange(len(f)), k)
    first = np.cumsum(k) - k
    j = np.arange(len(face)) - first[face]
    u = np.where(j == 0, 1 / 3, (j * 0.6180339887) % 1.0)  # the centre, then a golden-ratio walk over the triangle
    w = np.where(j == 0, 1 / 3, (j * 0.7548776662) % 1.0)
    flip = u + w > 1
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    c = tri[face, 0] + u[:, None] * (tri[face, 1] - tri[face, 0]) + w[:, None] * (tri[face, 2] - tri[face, 0])
    weight = 1.0 / k[face]

    def cells_of(x):
        return np.floor((x - lo) / cell).astype(np.int64) + 1  # a free cell on every side

    key, qkey = cells_of(c), cells_of(q)
    dims = np.maximum(key.max(axis=0), qkey.max(axis=0)) + 2
    cells, inv = np.unique(np.ravel_multi_index(key.T, tuple(dims)), return_inverse=True)
    inv = inv.reshape(-1)
    cn = np.stack([np.bincount(inv, n[face, i] * weight, len(cells)) for i in range(3)], axis=1)
    ca = np.bincount(inv, area[face] * weight, len(cells))
    qcells, qinv = np.unique(np.ravel_multi_index(qkey.T, tuple(dims)), return_inverse=True)
    qk = np.stack(np.unravel_index(qcells, tuple(dims)), axis=1)  # each distinct query cell once, in order
    box_n, box_a = np.zeros((len(qk), 3)), np.zeros(len(qk))
    for d in np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3):
        code = np.ravel_multi_index((qk + d).T, tuple(dims))
        at = np.minimum(np.searchsorted(cells, code), len(cells) - 1)
        hit = cells[at] == code
        box_n[hit] += cn[at[hit]]
        box_a[hit] += ca[at[hit]]
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = 1.0 - np.linalg.norm(box_n, axis=1) / box_a
    spread[~(box_a > 0)] = np.nan
    return np.clip(spread, 0.0, 1.0)[qinv.reshape(-1)]


@dataclass(frozen=True)
class _Rim:
    """One measurable view's outline: its index, camera, silhouette [H, W], outline pixels (rows, cols [K]), their
    hit faces [K] and barycentrics [K, 2], the pixels given to each [K], the mask outline's length and the footprint."""

    view: int
    camera: Camera
    hit: np.ndarray
    ry: np.ndarray
    rx: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    given: np.ndarray
    length: float
    foot: float


def _limb_points(rim: _Rim, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per outline pixel, [K, S, 3]: its hit point, then points on to where the hit face's plane meets the ray one
    pixel farther out (towards the nearest missed pixel), at most :data:`_REACH_PIXELS` footprints from the hit, in
    :data:`_REACH_STEPS` equal steps. A plane seen at a grazing angle ends at an edge far from its outline pixel's
    hit; one of the points lies near that edge (the last may lie past it, with no surface around)."""
    from scipy import ndimage

    cam, hit, ry, rx, b = rim.camera, rim.hit, rim.ry, rim.rx, rim.bary
    corners = v[f[rim.face]]  # [K, 3, 3]
    at = b[:, :1] * corners[:, 0] + b[:, 1:] * corners[:, 1] + (1.0 - b.sum(axis=1, keepdims=True)) * corners[:, 2]
    # outward: towards each outline pixel's nearest missed pixel (a distance transform of the silhouette's box, a
    # missed pixel around it)
    y0, x0 = ry.min(), rx.min()
    box = np.pad(hit[y0:ry.max() + 1, x0:rx.max() + 1], 1)
    _, (my, mx) = ndimage.distance_transform_edt(box, return_indices=True)
    ly, lx = ry - y0 + 1, rx - x0 + 1
    out = np.stack([my[ly, lx] - ly, mx[ly, lx] - lx], axis=1).astype(np.float64)
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    d = cam.pixel_directions_camera(ry + out[:, 0], rx + out[:, 1]) @ cam.R  # world directions, camera z = 1
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    o = np.asarray(cam.center, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = ((at - o) * n).sum(axis=1) / (d * n).sum(axis=1)
    step = o + t[:, None] * d - at
    size = np.linalg.norm(step, axis=1, keepdims=True)
    reach = _REACH_PIXELS * rim.foot
    step = np.where(np.isfinite(size) & (t[:, None] > 0), step * np.minimum(1.0, reach / np.maximum(size, 1e-30)), 0.0)
    return at[:, None] + np.linspace(0.0, 1.0, _REACH_STEPS + 1)[None, :, None] * step[:, None]


def outline_offset(verts, faces, cameras: Sequence, masks: Sequence, *, device: torch.device | str = "cpu",
                   raycaster=None) -> OutlineOffset:
    """How far the silhouettes of a mesh lie inside the masks along its smooth limbs, per view and as one distance.

    The silhouette is the mesh ray cast through each pixel centre, the mask thresholded at 0.5. Each pixel where they
    differ is given to the nearest outline pixel of the silhouette (+1 a mask pixel the silhouette misses, -1 a
    silhouette pixel outside the mask). An outline pixel lies on an edge when, at its hit or at points on its hit
    face's plane on to where that meets the next ray out, :func:`ridge_spread` over cells of
    :data:`RIDGE_CELL_PIXELS` times the views' median footprint is at least :data:`RIDGE_SPREAD` and more than
    :data:`RIDGE_GROWTH` times that over cells twice as large (a smooth surface bends about a quarter as much in the
    smaller box, an edge as much); otherwise on a smooth limb. Per view: the pixels given to smooth outline pixels
    over their share of the outline's length (the mask's, in pixels), times the pixel footprint at the median depth
    of the silhouette's outline (``z / fx``: the limb, where the offset is); the distance is their median over the
    views. On a view whose limbs are all smooth this is ``(mask area - silhouette area) / outline length``, which
    every view measures instead (``shares`` then 1) when its median over the views is negative: a silhouette that
    spills past the masks is too wide wherever it is, and a rounded edge only draws an outline in. Views
    whose mask touches the image border (the object is cut off: its outline there is the frame's) or whose mask or
    silhouette covers fewer than 64 pixels are not measurable; views with fewer than :data:`MIN_SMOOTH_PIXELS`
    outline pixels on smooth limbs are left out (``shares`` says how much of each measurable view's outline was
    smooth).

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
    from scipy import ndimage

    from ..raycast import MeshRaycaster

    if len(cameras) != len(masks):
        raise ValueError(f"masks must have one entry per camera ({len(cameras)}), got {len(masks)}")
    arrays = [_mask_array(i, m, c) for i, (m, c) in enumerate(zip(masks, cameras))]
    v = torch.as_tensor(np.ascontiguousarray(verts.detach().cpu() if torch.is_tensor(verts) else verts),
                        dtype=torch.float32)
    f = torch.as_tensor(np.ascontiguousarray(faces.cpu() if torch.is_tensor(faces) else faces), dtype=torch.int32)
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"verts must be finite, got {int((~torch.isfinite(v)).any(dim=-1).sum())} non-finite rows")
    caster = MeshRaycaster() if raycaster is None else raycaster  # one BVH for every view
    seen: list[_Rim] = []
    vd, fd = v.to(device), f.to(device)
    vn, fn = v.numpy().astype(np.float64), f.numpy().astype(np.int64)
    for i, (cam, mk) in enumerate(zip(cameras, arrays)):
        if mk.sum() < _MIN_PIXELS or mk[0].any() or mk[-1].any() or mk[:, 0].any() or mk[:, -1].any():
            continue
        with torch.no_grad():
            r = caster.raycast(vd, fd, cam)
        hit = r.mask.cpu().numpy().astype(bool)
        if hit.sum() < _MIN_PIXELS:
            continue
        inner = hit.copy()  # the silhouette's own pixels: a hit whose four neighbours are all hits is not one
        inner[1:-1, 1:-1] &= hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
        rim = hit & ~inner
        z = r.depth.cpu().numpy()[rim]
        z = float(np.median(z)) if len(z) else float("nan")
        if not (np.isfinite(z) and z > 0):
            continue  # no outline pixel (the silhouette fills the frame) or a degenerate hit
        length = float((mk[1:] != mk[:-1]).sum() + (mk[:, 1:] != mk[:, :-1]).sum()) * _EDGE_LENGTH
        ry, rx = np.nonzero(rim)
        # each differing pixel goes to its nearest outline pixel, within the box around the mask and the silhouette
        # (it holds every differing pixel and every outline pixel)
        ys, xs = np.nonzero(mk | hit)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        slot = np.full((y1 - y0, x1 - x0), -1, dtype=np.int64)
        slot[ry - y0, rx - x0] = np.arange(len(ry))
        diff = mk[y0:y1, x0:x1].astype(np.int64) - hit[y0:y1, x0:x1].astype(np.int64)
        dy, dx = np.nonzero(diff)
        _, (ny, nx) = ndimage.distance_transform_edt(slot < 0, return_indices=True)
        given = np.bincount(slot[ny[dy, dx], nx[dy, dx]], diff[dy, dx], len(ry))
        seen.append(_Rim(i, cam, hit, ry, rx, r.face_id.cpu().numpy()[ry, rx],
                         r.bary.cpu().numpy()[ry, rx].astype(np.float64), given, length, z / float(cam.K[0, 0])))
    if not seen:
        return OutlineOffset(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0))
    whole = np.asarray([float(s.given.sum()) / s.length for s in seen])
    feet = np.asarray([s.foot for s in seen])
    if np.median(whole * feet) < 0:
        # the silhouettes spill past the masks: too wide wherever they are, edges included (a rounded edge only
        # draws an outline in), so every outline pixel counts
        return OutlineOffset(whole, feet, np.asarray([s.view for s in seen]), np.ones(len(seen)))
    cell = RIDGE_CELL_PIXELS * float(np.median(feet))
    pts = np.concatenate([_limb_points(s, vn, fn).reshape(-1, 3) for s in seen])
    fine, coarse = ridge_spread(vn, fn, pts, cell), ridge_spread(vn, fn, pts, 2.0 * cell)
    # an edge bends within the finer box about as much as within the coarser one; a smooth surface about a quarter
    # as much (NaN, no surface in the box where the hit's plane meets the next ray out: it has curved away)
    edge = ((fine >= RIDGE_SPREAD) & (fine > RIDGE_GROWTH * coarse)).reshape(-1, _REACH_STEPS + 1)
    smooth_all = ~edge.any(axis=1)
    pix, used, shares, start = [], [], [], 0
    for k, s in enumerate(seen):
        smooth = smooth_all[start:start + len(s.ry)]
        start += len(s.ry)
        shares.append(float(smooth.mean()))
        if smooth.sum() >= MIN_SMOOTH_PIXELS:
            # the smooth outline's length: its share of the pixels times the whole outline's length
            pix.append(float(s.given[smooth].sum()) / (s.length * shares[-1]))
            used.append(k)
    return OutlineOffset(np.asarray(pix, dtype=np.float64), feet[used],
                         np.asarray([seen[k].view for k in used], dtype=np.int64), np.asarray(shares, dtype=np.float64))


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
