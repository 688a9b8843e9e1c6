# SPDX-License-Identifier: Apache-2.0
"""TSDF fusion of rendered surfel depth (the Warp kernel of :mod:`wtopo.tsdf_fusion`, on CPU or CUDA) and the
TSDF re-initialisation of the surfels.

Bounds, voxel size, truncation and the per-view depth cut-off are derived from the cameras and
the current surfels, never given by hand: the bounds are a robust box around the opaque surfels
(clipped to the normalised scene), the voxel size divides the box's longest side into
``resolution`` voxels, the truncation is a fixed number of voxels, and each view's depth cut-off is
the farthest corner of the bounds from that camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from .._profile import section
from ..camera import Camera
from ..geometry.mesh_policy import keep_faces
from ..geometry.winding import boundary_edges, is_closed, orient_faces
from ..scene import NORMALIZATION_MARGIN
from .surfels import Surfels

__all__ = ["TSDFEmptyError", "FusionBounds", "auto_bounds", "fuse_depths", "mesh_to_surfels", "cleanup_mesh",
           "repair_mesh", "fill_boundary_loops", "hybrid_keep"]

_BOX_PERCENTILE = 0.5  # percent of surfels ignored on each side when boxing them (floaters)
_BOX_MARGIN = 0.05  # box grows by this fraction of its longest side on every side
# the region of interest fills [m, 1 - m]^3 (Scene.normalization, m = NORMALIZATION_MARGIN); never fuse
# farther than one more margin outside the unit cube
_SCENE_LIMIT = (-NORMALIZATION_MARGIN, 1.0 + NORMALIZATION_MARGIN)
_MIN_OPACITY = 0.1  # surfels below this opacity do not shape the bounds
_FAN_MAX_EDGES = 48  # repair_mesh caps boundary loops of at most this many edges with a fan (larger: Poisson)


class TSDFEmptyError(RuntimeError):
    """TSDF fusion produced no surface."""


@dataclass
class FusionBounds:
    """Automatic fusion parameters in the internal frame."""

    lower: np.ndarray
    upper: np.ndarray
    voxel: float
    truncation: float

    def to_dict(self) -> dict:
        """JSON-ready bounds, voxel size and truncation."""
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist(), "voxel": self.voxel,
                "truncation": self.truncation}


def auto_bounds(points: torch.Tensor | np.ndarray, weights: torch.Tensor | np.ndarray | None, *,
                resolution: int, truncation_voxels: float) -> FusionBounds:
    """Bounds around ``points`` [N, 3] (surfel centres, weighted by opacity when given).

    Points with weight below 0.1 are ignored (unless fewer than 8 remain); the box spans the
    ``[0.5, 99.5]`` percentiles plus a 5 % margin, clipped to the normalised scene.
    """
    p = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
    if weights is not None:
        w = weights.detach().cpu().numpy() if isinstance(weights, torch.Tensor) else np.asarray(weights)
        sel = w >= _MIN_OPACITY
        if sel.sum() >= 8:
            p = p[sel]
    if p.shape[0] == 0:
        lo, hi = np.zeros(3), np.ones(3)
    else:
        lo = np.percentile(p, _BOX_PERCENTILE, axis=0)
        hi = np.percentile(p, 100 - _BOX_PERCENTILE, axis=0)
    side = float(np.max(hi - lo))
    side = side if side > 1e-6 else 1.0
    lo = np.clip(lo - _BOX_MARGIN * side, *_SCENE_LIMIT)
    hi = np.clip(hi + _BOX_MARGIN * side, *_SCENE_LIMIT)
    voxel = float(np.max(hi - lo)) / resolution
    return FusionBounds(lo, hi, voxel, truncation_voxels * voxel)


def _far_depth(camera: Camera, bounds: FusionBounds) -> float:
    corners = np.array([[x, y, z] for x in (bounds.lower[0], bounds.upper[0])
                        for y in (bounds.lower[1], bounds.upper[1]) for z in (bounds.lower[2], bounds.upper[2])])
    _, z = camera.project(corners)
    return float(max(z.max(), 1e-6)) + bounds.truncation


def fuse_depths(cameras: Sequence[Camera], depths: Sequence[np.ndarray], colors: Sequence[np.ndarray],
                bounds: FusionBounds, *, device: torch.device | str = "cpu", close: bool = False) -> trimesh.Trimesh:
    """Fuse z-depth maps into a TSDF and extract its mesh, cropped to ``bounds``.

    :func:`wtopo.tsdf_fusion.fuse_tsdf` on ``device`` (CPU or CUDA) integrates each view along its camera's own
    per-pixel rays (principal point, skew and OpenCV distortion, every node projected through the lens):
    truncation ``bounds.truncation``, per-view depth cut-off at the farthest corner of the bounds, weight 1
    per view, depth 0 (or NaN / inf) = no data; the surface is open where no view observed the grid.
    Not differentiable.

    Args:
        cameras: one camera per depth map (internal frame).
        depths: z-depth [H, W] float (0 = no measurement), internal units, in the camera's pixel grid.
        colors: RGB [H, W, 3] float in [0, 1].
        bounds: from :func:`auto_bounds`.
        device: where the fusion runs.
        close: close the surface by space carving (:func:`wtopo.tsdf_fusion.fuse_tsdf`'s ``close``:
            unobserved space no view saw empty is inside).

    Returns:
        A vertex-coloured mesh in the internal frame.

    Raises:
        ValueError: a depth or colour map whose size is not its camera's image size.
        TSDFEmptyError: no surface (every depth empty, or depths in other units than the cameras).
    """
    views = []
    for cam, dep, col in zip(cameras, depths, colors):
        dep = np.ascontiguousarray(np.nan_to_num(np.asarray(dep, np.float32), nan=0.0, posinf=0.0, neginf=0.0))
        if dep.shape != (cam.height, cam.width) or np.shape(col)[:2] != (cam.height, cam.width):
            raise ValueError(f"depth and colour of camera {cam.name!r} must be [{cam.height}, {cam.width}] "
                             f"(its image size), got {list(dep.shape)} and {list(np.shape(col))}")
        if (dep > 0).any():
            views.append((cam, dep, np.clip(np.asarray(col, np.float32), 0, 1)))
    v = f = c = np.zeros((0, 3))
    with section("tsdf_fusion"):
        if views:
            v, f, c = _fuse_warp(views, bounds, device, close=close)
    if not views or f.shape[0] == 0:
        raise TSDFEmptyError(
            f"TSDF fusion of {len(depths)} depth maps ({len(views)} with valid pixels) produced no surface; "
            f"voxel {bounds.voxel:.4g}, truncation {bounds.truncation:.4g} (internal units). Depths must be "
            "z-depths in the cameras' units (Open3D #4419: a wrong depth scale or a cut-off below the scene).")
    # marching cubes shares each edge's vertex already: no merge by position (2.6M faces: seconds; see cleanup_mesh)
    tm = trimesh.Trimesh(v, f, vertex_colors=c if c.size else None, process=False)
    inside = np.all((tm.vertices >= bounds.lower - bounds.voxel) & (tm.vertices <= bounds.upper + bounds.voxel), axis=1)
    if not inside.all():
        tm.update_faces(inside[tm.faces].all(axis=1))
        tm.remove_unreferenced_vertices()
    if len(tm.faces) == 0:
        raise TSDFEmptyError("TSDF mesh lies entirely outside the automatic bounds")
    return tm


def _fuse_warp(views: list, bounds: FusionBounds, device, *,
               close: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`wtopo.tsdf_fusion.fuse_tsdf` of ``views`` ``(camera, depth, colour)`` on ``device``
    (``close``: carved shut)."""
    from ..tsdf_fusion import fuse_tsdf

    cams = [cam for cam, _, _ in views]
    m = fuse_tsdf(cams, [d for _, d, _ in views], [c for _, _, c in views], lower=bounds.lower, upper=bounds.upper,
                  voxel=bounds.voxel, truncation=bounds.truncation, far=[_far_depth(c, bounds) for c in cams],
                  device=device, close=close)
    return m.verts.cpu().numpy(), m.faces.cpu().numpy(), m.colors.cpu().numpy()


def cleanup_mesh(mesh: trimesh.Trimesh, *, largest_component: bool = True, repair: bool = True,
                 weld: bool = True) -> trimesh.Trimesh:
    """Merge vertices, drop degenerate faces, keep the largest component (``largest_component``), and
    with ``repair`` fill small holes and orient the faces (``False`` for open scene meshes).

    ``weld=False`` keeps the mesh's own vertex sharing (a marching-cubes mesh shares each edge's vertex
    already): vertices are not merged by position and only faces that repeat a vertex index go. At fine grids
    (768^3) float32 rounds edge vertices a few 1e-5 cells from a grid node onto it; merging those by position
    collapsed faces into non-manifold edges and left the Poisson re-mesh of a GPU fit open."""
    if weld:
        mesh = mesh.copy()
        mesh.merge_vertices()
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
    else:  # a new mesh of the faces that repeat no index and their vertices (trimesh's copy and cache: 0.3 s at 1M)
        f = np.asarray(mesh.faces)
        mesh = keep_faces(mesh, (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    if largest_component and len(mesh.faces):
        parts = mesh.split(only_watertight=False)
        if len(parts) > 1:
            mesh = max(parts, key=lambda m: len(m.faces))
    if repair:
        repair_mesh(mesh)
    return mesh


def repair_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Fill small holes (:func:`fill_boundary_loops` up to ``_FAN_MAX_EDGES`` edges: a surface cut by the fusion
    box leaves a loop of a few edges on the box's face; then trimesh's ``fill_holes`` for the three- and
    four-edge holes through a pinched vertex, which it can close and the loops cannot) of a mesh that is
    not closed and orient its faces
    (:func:`~.winding.orient_faces`: neighbours agree, each part as most of its faces are; a closed mesh
    of negative volume is turned), in place. It leaves whether the result is closed in
    ``mesh.metadata["closed"]`` (the caller need not test the edges again: about a second on 2.6M faces).

    Run it after the components that no view supports are dropped (:func:`~.mesh_policy.supported_components`),
    not before: a 512-px fit's final TSDF mesh has 20,000-30,000 components, nearly all of them specks, and
    filling their holes first kept the fit on one CPU core for minutes. The faces were oriented by trimesh's
    ``fix_normals``, a breadth-first walk in Python: over 15 minutes on a ten-view cup's 512-px mesh. Closedness
    is :func:`~.winding.is_closed` and the inward test :func:`signed_volume` (trimesh's ``is_watertight`` and
    mass properties took 10 of the 22 s this took on a 2.6M-face mesh on 2 cores)."""
    closed = is_closed(mesh.faces)
    if not closed:
        fill_boundary_loops(mesh, _FAN_MAX_EDGES)
        closed = is_closed(mesh.faces)
    if not closed:  # trimesh's search costs seconds on millions of faces: only what the loops left
        trimesh.repair.fill_holes(mesh)
        closed = is_closed(mesh.faces)
    mesh.faces = orient_faces(mesh.faces)  # the same edges, rewound: closed or not as before
    if closed and signed_volume(mesh) < 0.0:  # a closed mesh of negative volume points inwards
        mesh.invert()
    mesh.metadata["closed"] = closed
    return mesh


def signed_volume(mesh: trimesh.Trimesh) -> float:
    """The volume the faces enclose, negative when they wind inwards (meaningful for a closed mesh); one
    vectorised sum, where trimesh's mass properties took seconds on millions of faces."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0:
        return 0.0
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def fill_boundary_loops(mesh: trimesh.Trimesh, max_edges: int) -> int:
    """Cap every simple boundary loop of at most ``max_edges`` edges: three and four edges with one and two
    triangles (as trimesh's ``fill_holes``), longer ones with a fan of triangles around the loop's centroid (a
    new vertex; coloured as the loop's mean where the mesh has vertex colours); wound against the loop's own
    faces so the neighbours agree; in place.

    A loop is simple when each of its vertices starts exactly one boundary edge; loops through a vertex
    where several boundary edges meet are left open. Returns the number of loops capped."""
    f = np.asarray(mesh.faces, np.int64)
    if len(f) == 0:
        return 0
    border = boundary_edges(f)  # each as its face winds it, a -> b
    if len(border) == 0:
        return 0
    starts, n_out = np.unique(border[:, 0], return_counts=True)
    simple = set(starts[n_out == 1].tolist())
    nxt = {int(a): int(b) for a, b in border if int(a) in simple}
    seen: set[int] = set()
    loops = []
    for a0 in nxt:
        if a0 in seen:
            continue
        loop, a = [], a0
        while a in nxt and a not in seen:
            seen.add(a)
            loop.append(a)
            a = nxt[a]
        if a == a0 and 3 <= len(loop) <= max_edges:
            loops.append(loop)
    if not loops:
        return 0
    v = np.asarray(mesh.vertices)
    colors = mesh.visual.vertex_colors if mesh.visual.kind == "vertex" else None
    new_v, new_f, new_c = [], [], []
    for loop in loops:
        a = np.asarray(loop)
        if len(a) == 3:  # one triangle, as trimesh's fill_holes caps it: the edges a -> b read as b -> a
            new_f.append(a[[0, 2, 1]][None])
            continue
        if len(a) == 4:  # two triangles across the diagonal a0 - a2
            new_f.append(np.stack([a[[0, 3, 2]], a[[0, 2, 1]]]))
            continue
        c = len(v) + len(new_v)
        new_v.append(v[loop].mean(axis=0))
        if colors is not None:
            new_c.append(np.asarray(colors)[loop].mean(axis=0))
        b = np.roll(a, -1)
        new_f.append(np.stack([b, a, np.full_like(a, c)], axis=1))  # the edge a -> b read as b -> a
    verts = np.concatenate([v, np.asarray(new_v).reshape(-1, 3)])
    faces = np.concatenate([f, *new_f])
    vc = None if colors is None else np.concatenate([np.asarray(colors),
                                                     np.round(np.asarray(new_c).reshape(-1, 4)).astype(np.uint8)])
    mesh.vertices = verts
    mesh.faces = faces
    if vc is not None:
        mesh.visual.vertex_colors = vc
    return len(loops)


def mesh_to_surfels(mesh: trimesh.Trimesh, *, max_faces: int, device: torch.device | str, sh_degree: int,
                    opacity: float) -> Surfels:
    """One surfel per triangle of ``mesh`` (decimated to at most ``max_faces``).

    Centre at the centroid, normal = face normal, first tangent along the first edge, both scales
    ``sqrt(area / pi)`` (a disc of one sigma has the triangle's area, so neighbours overlap and the
    surface is covered from the start), colour the mean of the vertex colours; the normal's sign is
    the triangle's and marked as a mesh's (``buffers["mesh_sign"]``). The decimation is
    :func:`decimate` (quadric edge collapse).
    """
    mesh = decimate(mesh, int(max_faces))
    v = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    f = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.long)
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cr = torch.cross(e1, e2, dim=-1)
    area = 0.5 * cr.norm(dim=-1)
    keep = area > 1e-12
    tri, cr, area, e1, f = tri[keep], cr[keep], area[keep], e1[keep], f[keep]
    if mesh.visual.kind == "vertex":
        vc = torch.as_tensor(np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0, dtype=torch.float32)
        col = vc[f].mean(dim=1)
    else:
        col = torch.full((f.shape[0], 3), 0.5)
    scale = torch.sqrt(area / np.pi)
    s = Surfels.from_points(tri.mean(dim=1), col, scales=scale, normals=cr, tangents=e1, opacity=opacity,
                            sh_degree=sh_degree)
    s.buffers["mesh_sign"].fill_(1.0)  # the triangle's side: a sign refresh keeps it (align_normal_signs)
    return _to(s, device)


def decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """``mesh`` reduced to at most ``max_faces`` faces by quadric edge collapse (Garland and Heckbert,
    1997; the ``fast_simplification`` library). Each kept vertex takes the colour of the input vertex
    nearest to it. Not differentiable.

    Args:
        mesh: triangle mesh, optionally with vertex colours.
        max_faces: most faces of the result, >= 1.

    Returns:
        A new mesh (``process=False``); ``mesh`` itself when it already has at most ``max_faces`` faces.
    """
    if isinstance(max_faces, bool) or int(max_faces) != max_faces or max_faces < 1:
        raise ValueError(f"max_faces must be a positive integer, got {max_faces!r}")
    if len(mesh.faces) <= max_faces:
        return mesh
    import fast_simplification
    from scipy.spatial import cKDTree

    verts = np.asarray(mesh.vertices, dtype=np.float64)
    v, f = fast_simplification.simplify(verts, np.asarray(mesh.faces, dtype=np.int32),
                                        target_count=int(max_faces))
    if len(f) > max_faces:  # the library documents that a collapse may stop short of its target: once more
        v, f = fast_simplification.simplify(v, f.astype(np.int32), target_count=int(max_faces) - (len(f) - max_faces))
    colors = None
    if mesh.visual.kind == "vertex":
        near = cKDTree(verts).query(v, workers=-1)[1]
        colors = np.asarray(mesh.visual.vertex_colors)[near]
    return trimesh.Trimesh(v, f, vertex_colors=colors, process=False)


def _to(s: Surfels, device) -> Surfels:
    return Surfels.from_state_dict(s.state_dict(), device)


def hybrid_keep(old: Surfels, distance: torch.Tensor, max_distance: float) -> dict:
    """Parameters and buffers of the old surfels farther than ``max_distance`` from the TSDF mesh."""
    idx = torch.nonzero(distance > max_distance).flatten()
    return old.take(idx)

