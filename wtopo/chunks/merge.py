# SPDX-License-Identifier: Apache-2.0
"""Merge chunk results into one mesh: re-fuse the merged surfels (default) or weld the chunks' meshes.

Both keep, of each chunk, what lies in its core (:func:`~.partition.core_owner`: the cores partition
space, so nothing is kept twice or lost between two chunks): surfels by centre
(:func:`merge_surfels`), faces by centroid (:func:`keep_core_faces`).

``ChunkConfig.merge = "refuse"`` (:func:`refuse_mesh`): the merged surfels are the one surface, and
the fit's own final meshing (:func:`wtopo.fitting.final_mesh`: TSDF fusion of their rendered
depth in every training view, then the scene's meshing policy) runs once over the whole region of
interest, in the whole scene's internal frame and at the finest voxel size the chunks' own final
meshes used. One fusion grid spans every cut, so there is no seam to close: marching cubes of one
grid is closed across any plane. The grid is never dense in memory: the Warp backend fuses it one
z-slab at a time (:data:`wtopo.tsdf_fusion.SLAB_NODES` nodes, about 350 MB, whatever the grid size)
and Open3D's ``ScalableTSDFVolume`` keeps only the blocks near the surface.

``ChunkConfig.merge = "weld"`` (:func:`merge_meshes`): the chunks' meshes are cut to their cores,
concatenated, and the vertices on their open boundaries that lie near a cut are welded to the
nearest boundary vertex of the neighbouring chunk within a tolerance (``ChunkConfig.weld_fraction``
of the median boundary edge length).

Limitations:
    Welding snaps vertices, it does not re-triangulate: where two chunks' surfaces differ by more
    than the tolerance across a cut, a crack of that size stays. Re-fusing renders every training
    view once more on rank 0 (one device), and holds their depth and colour maps on the host (16
    bytes per pixel) and, with the Warp backend, on the device (about 18 bytes per pixel).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import trimesh

from .partition import ChunkPlan, core_owner, grid_owner

__all__ = ["keep_core_faces", "weld_boundaries", "merge_meshes", "merge_surfels", "boundary_edges_near", "refuse_mesh",
           "refuse_resolution", "MAX_REFUSE_RESOLUTION"]

MAX_REFUSE_RESOLUTION = 4096
"""Most voxels along the longest side of the re-fusion grid: beyond it the voxel grows (recorded in the
merge report). Memory does not depend on it (the fusion is slab by slab or sparse); the fusion time
and the mesh grow with it."""


def keep_core_faces(mesh: trimesh.Trimesh, plan: ChunkPlan, index: int) -> trimesh.Trimesh:
    """The faces of ``mesh`` (world frame) whose centroid lies in chunk ``index``'s core."""
    if len(mesh.faces) == 0:
        return mesh.copy()
    keep = core_owner(mesh.triangles_center, plan) == index
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out


def _open_edges(faces: np.ndarray) -> np.ndarray:
    """Edges [E, 2] (sorted vertex pairs) used by exactly one face."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    return uniq[count == 1]


def boundary_edges_near(mesh: trimesh.Trimesh, cuts, band: float) -> int:
    """Open edges of ``mesh`` whose midpoint lies within ``band`` of a cut plane ``(axis, coordinate)``:
    the seam's cracks (0 when the merge closed it)."""
    if len(mesh.faces) == 0 or not cuts:
        return 0
    e = _open_edges(np.asarray(mesh.faces))
    mid = 0.5 * (mesh.vertices[e[:, 0]] + mesh.vertices[e[:, 1]])
    near = np.zeros(len(e), bool)
    for a, c in cuts:
        near |= np.abs(mid[:, a] - c) <= band
    return int(near.sum())


def weld_boundaries(pieces: list[trimesh.Trimesh], cuts, tolerance: float | None, fraction: float
                    ) -> tuple[trimesh.Trimesh, dict]:
    """Concatenate ``pieces`` and weld open-boundary vertices of different pieces near the ``cuts``.

    Args:
        pieces: one mesh per chunk (world frame), already reduced to its core.
        cuts: interior cut planes ``(axis, coordinate)``.
        tolerance: weld distance, world units; ``None``: ``fraction`` of the median open-edge length.
        fraction: see ``tolerance``.

    Returns:
        ``(mesh, info)``: the merged mesh and the weld counts (tolerance, welded vertices, open
        edges near the cuts before and after).
    """
    pieces = [p for p in pieces if len(p.faces)]
    if not pieces:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False), {"welded": 0}
    verts, faces, owner, off = [], [], [], 0
    for k, p in enumerate(pieces):
        verts.append(np.asarray(p.vertices, np.float64))
        faces.append(np.asarray(p.faces, np.int64) + off)
        owner.append(np.full(len(p.vertices), k))
        off += len(p.vertices)
    v, f, own = np.concatenate(verts), np.concatenate(faces), np.concatenate(owner)
    open_e = _open_edges(f)
    lengths = np.linalg.norm(v[open_e[:, 0]] - v[open_e[:, 1]], axis=1)
    tol = float(tolerance) if tolerance is not None else (fraction * float(np.median(lengths)) if len(lengths) else 0.0)
    bverts = np.unique(open_e)
    near = np.zeros(len(bverts), bool)
    for a, c in cuts:
        near |= np.abs(v[bverts, a] - c) <= 2.0 * tol
    cand = bverts[near]
    before = boundary_edges_near(trimesh.Trimesh(v, f, process=False), cuts, 2.0 * tol) if tol > 0 else 0
    parent = np.arange(len(v))
    welded = 0
    if len(cand) > 1 and tol > 0:
        from scipy.spatial import cKDTree

        pairs = cKDTree(v[cand]).query_pairs(tol, output_type="ndarray")
        pairs = pairs[own[cand[pairs[:, 0]]] != own[cand[pairs[:, 1]]]]  # only across chunks
        d = np.linalg.norm(v[cand[pairs[:, 0]]] - v[cand[pairs[:, 1]]], axis=1)
        used = np.zeros(len(v), bool)
        for i in np.argsort(d):  # closest pairs first; each vertex welds once (a matching, no chains)
            a, b = cand[pairs[i, 0]], cand[pairs[i, 1]]
            if used[a] or used[b]:
                continue
            used[a] = used[b] = True
            mid = 0.5 * (v[a] + v[b])
            v[a] = mid
            parent[b] = a
            welded += 1
    f = parent[f]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    f = f[good]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    mesh = trimesh.Trimesh(v, f, process=False)
    mesh.remove_unreferenced_vertices()
    after = boundary_edges_near(mesh, cuts, 2.0 * tol) if tol > 0 else 0
    return mesh, {"tolerance": tol, "welded": welded, "open_edges_near_cuts_before": before,
                  "open_edges_near_cuts_after": after}


def merge_meshes(meshes: dict, plan: ChunkPlan, *, tolerance: float | None = None, fraction: float = 0.75
                 ) -> tuple[trimesh.Trimesh, dict]:
    """Keep each chunk's core faces and weld the pieces (see the module docstring).

    Args:
        meshes: ``{chunk index: trimesh.Trimesh}`` in the world frame.
        plan: the :class:`~.partition.ChunkPlan` they were fitted under.
        tolerance: weld distance in world units, or ``None`` (``fraction`` of the median open-edge length).
        fraction: see ``tolerance``.

    Returns:
        ``(mesh, info)``.
    """
    pieces = [keep_core_faces(m, plan, i) for i, m in sorted(meshes.items())]
    mesh, info = weld_boundaries(pieces, plan.cuts(), tolerance, fraction)
    info["faces_per_chunk"] = {int(i): int(len(p.faces)) for i, p in zip(sorted(meshes), pieces)}
    return mesh, info


def merge_surfels(surfels: dict, plan: ChunkPlan):
    """Concatenate each chunk's surfels whose centre lies in its core.

    Args:
        surfels: ``{chunk index: wtopo.io.SurfelArrays}`` in the world frame (``read_surfels_ply``).
        plan: the chunk plan.

    Returns:
        ``(means, quats, scales, opacities, sh)`` float32 arrays, SH padded to the highest degree.
    """
    keep = []
    for i, s in sorted(surfels.items()):
        sel = core_owner(s.means, plan) == i
        keep.append((s, sel))
    k = max((s.sh.shape[1] for s, _ in keep), default=1)
    cat = lambda get: np.concatenate([get(s)[sel] for s, sel in keep]) if keep else np.zeros((0,))  # noqa: E731
    sh = np.concatenate([np.pad(s.sh[sel], ((0, 0), (0, k - s.sh.shape[1]), (0, 0))) for s, sel in keep]) \
        if keep else np.zeros((0, 1, 3), np.float32)
    return (cat(lambda s: s.means), cat(lambda s: s.quats), cat(lambda s: s.scales), cat(lambda s: s.opacities), sh)


def refuse_resolution(plan: ChunkPlan, resolutions: dict) -> int:
    """Voxels along the region of interest's longest side that give the re-fusion the finest voxel
    the chunks' own final meshes had.

    A chunk fitted as a scene fuses its box (its region of interest) grown by the same fraction on
    every side with ``resolutions[i]`` voxels along the longest side, so its voxel is
    ``side_i * (1 + 2 m) / resolutions[i]``; the whole region's fusion has the same margin ``m``,
    which cancels: the result is ``max_i resolutions[i] * side / side_i``, rounded up and capped at
    :data:`MAX_REFUSE_RESOLUTION`.

    Args:
        plan: the chunk plan (boxes and region of interest, world units).
        resolutions: ``{chunk index: the chunk fit's resolved final.resolution}`` (int).

    Returns:
        int, at least the largest of ``resolutions``.
    """
    if not resolutions:
        raise ValueError("resolutions must name at least one chunk's final resolution, got none")
    side = float(np.max(plan.roi_upper - plan.roi_lower))
    need = max(int(r) * side / float(np.max(plan.chunks[i].upper - plan.chunks[i].lower))
               for i, r in resolutions.items())
    return int(min(MAX_REFUSE_RESOLUTION, max(max(resolutions.values()), math.ceil(need - 1e-9))))


def _core_renderer(base, plan: ChunkPlan, sim, views: dict):
    """A :class:`wtopo.fitting.Renderer` that renders as ``base`` does and then sets alpha to 0 on
    the pixels whose surface (the rendered median z-depth, back-projected) lies in the core of a
    chunk the view did not fit. ``views``: ``{id(camera): bool tensor [chunks]}``, the chunks each
    (internal-frame) camera was given; other cameras render unchanged."""
    import torch

    from ..fitting import Renderer

    # the region of interest in the internal frame (the similarity only scales and shifts), on the device once
    lo, hi = (torch.as_tensor(sim.to_internal(b), dtype=torch.float32, device=base.background.device)
              for b in (plan.roi_lower, plan.roi_upper))

    class _CoreViews(Renderer):
        def __call__(self, surfels, camera, *, defer_count: bool = False):
            out = super().__call__(surfels, camera, defer_count=defer_count)
            allowed = views.get(id(camera))
            if allowed is None:
                return out
            z = out.median_depth
            o, d = camera.pixel_rays(z.device)
            owner = grid_owner(o + d * z[..., None], lo, hi, plan.grid)
            return dataclasses.replace(out, alpha=torch.where(allowed[owner], out.alpha, torch.zeros_like(out.alpha)))

    core = _CoreViews(base.background, base.config)
    # what the views see, unmasked: the final mesh's per-face view support compares the mesh with it (a masked
    # pixel says which chunk vouches for a surface there, not that no surface is there)
    core.unmasked = base
    return core


def chunk_near(scene, plan: ChunkPlan) -> float:
    """The smallest near-camera distance (world units) of the chunks' own fits: the meshing policy's
    "no face within the near distance of a camera" (:mod:`wtopo.fitting.scene_kind`) scales with the
    extent of the scene it is given, and the whole scene's extent would remove real surface (the
    ground under a camera) that every chunk kept. Each chunk's is
    :func:`wtopo.fitting.near_distance` of its cameras around its box (what its fit's
    layout computes in the internal frame, here in world units)."""
    from ..fitting import near_distance

    near = math.inf
    for ch in plan.chunks:
        if len(ch.cameras) == 0:
            continue
        centers = np.stack([scene.cameras[int(i)].center for i in ch.cameras])
        near = min(near, near_distance(centers, ch.lower, ch.upper)[0])
    return near


def refuse_mesh(scene, surfels, config, *, resolution: int, device: str = "cpu", plan: ChunkPlan | None = None
                ) -> tuple[trimesh.Trimesh, dict]:
    """The fit's own final mesh of ``surfels`` over the whole of ``scene``: the merge without seams.

    The scene is normalised and planned as :func:`wtopo.fit` does it (:meth:`wtopo.Scene.normalization`,
    :func:`wtopo.fitting.make_plan`: scene kind, region of interest, background, image scale,
    TSDF backend), the surfels are mapped into that internal frame, and
    :func:`wtopo.fitting.final_mesh` renders their depth in every training view of the scene
    (one view at a time, on ``device``), fuses it into one TSDF over the region of interest at
    ``resolution`` voxels along its longest side, and applies the meshing policy (crop to the
    region, nothing near a camera, components the views support). Nothing is fitted.

    Args:
        scene: the whole :class:`wtopo.Scene` (world frame); only its cameras, split and region are
            used by the meshing (the plan reads its images).
        surfels: ``(means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 2], opacities [N], sh [N, K, 3])``
            float32 NumPy arrays, world frame (:func:`merge_surfels`); scales are standard deviations
            in world units, opacities in (0, 1).
        config: the :class:`wtopo.FitConfig` the chunks ran (its ``final``, ``tsdf``, ``mesh`` and
            ``filter_sigma`` settings; ``final.resolution`` is replaced by ``resolution``).
        resolution: TSDF voxels along the longest side of the fusion bounds (:func:`refuse_resolution`).
        device: where the surfels are rendered and, with the Warp backend, fused.
        plan: the chunk plan the surfels were fitted under, or ``None``. With it, a view fuses only
            the pixels whose rendered surface lies in the core of a chunk it was given (the chunk's
            surfels elsewhere were never fitted to it: a floater that no view of that chunk sees
            would otherwise be fused from this one); occlusion is still by every surfel.

    Returns:
        ``(mesh, info)``: the mesh in the world (the caller's) frame and a JSON-ready record (voxel in
        world units, resolution, fusion bounds, views, the meshing policy's events).

    Raises:
        wtopo.fitting.tsdf.TSDFEmptyError: nothing was fused and the Poisson fallback is empty.
    """
    import copy

    import torch

    from ..fitting import ProxyMesh, Renderer, Surfels, Timers, final_mesh, make_plan, resolve_config
    from ..rasterize import RasterConfig

    means, quats, scales, opacities, sh = surfels
    dev = torch.device(device)
    sim = scene.normalization()
    internal = scene.normalized()
    user = copy.deepcopy(config)
    user.final.resolution = int(resolution)  # an override: the plan records it and resolve_config keeps it
    fplan = make_plan(internal, user, dev)
    cfg = resolve_config(user, fplan)
    train = range(len(internal)) if internal.train_indices is None else internal.train_indices
    scale = float(cfg.runtime.image_scale)
    cams = [internal.cameras[int(i)] for i in train]
    cams = [c.scaled(scale) for c in cams] if scale < 1.0 else cams
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=dev)  # noqa: E731
    sh = np.asarray(sh, np.float32).reshape(len(means), -1, 3)
    s = Surfels(means=t(sim.to_internal(np.asarray(means, np.float64))), quats=t(quats),
                log_scales=torch.log(t(np.asarray(scales, np.float64) * sim.scale).clamp_min(1e-12)),
                opacity_logits=torch.logit(t(opacities), eps=1e-6), sh_dc=t(sh[:, :1]), sh_rest=t(sh[:, 1:]))
    render = Renderer(torch.tensor(cfg.background, dtype=torch.float32, device=dev),
                      RasterConfig(filter_sigma=cfg.filter_sigma))
    layout = fplan.layout
    if plan is not None:
        given = {}
        for ch in plan.chunks:
            for i in ch.cameras:
                given.setdefault(int(i), set()).add(ch.index)
        mask = lambda i: torch.as_tensor([k in given.get(int(i), ()) for k in range(len(plan.chunks))],  # noqa: E731
                                         device=dev)
        render = _core_renderer(render, plan, sim, {id(c): mask(i) for i, c in zip(train, cams)})
        # the near-camera distance the chunks meshed with, not the whole scene's (chunk_near)
        layout = dataclasses.replace(layout, near=min(layout.near, sim.scale * chunk_near(scene, plan)))
    events, tsdf_info = [], {}
    timers = Timers(torch.cuda.synchronize if dev.type == "cuda" else None)
    t0 = time.perf_counter()
    with timers("final"):
        mesh = final_mesh(s, cams, cfg, render=render, proxy=ProxyMesh(cfg.mesh), guided=bool(cfg.coevolution.enabled),
                          tsdf_info=tsdf_info, record=lambda event, **kw: events.append({"event": event, **kw}),
                          layout=layout)
    prof = timers.profile(time.perf_counter() - t0)
    bounds = tsdf_info.get("final_bounds")
    info = {"method": "refuse", "resolution": int(resolution), "views": len(cams), "surfels": int(len(means)),
            "views_per_chunk_core": plan is not None, "scene_kind": cfg.kind.value,
            "near": float(sim.length_to_world(layout.near)),
            "voxel": None if bounds is None else float(sim.length_to_world(bounds["voxel"])),
            "final_bounds_internal": bounds, "events": events,
            "profile_s": {r["path"]: round(r["self_s"], 3) for r in prof["rows"]}}
    return sim.to_world(mesh), info
