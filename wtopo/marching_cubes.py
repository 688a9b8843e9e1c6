# SPDX-License-Identifier: Apache-2.0
"""Differentiable marching cubes: a scalar grid to a welded, outward-wound triangle mesh.

count -> scan -> write over node columns cut into z-chunks (see :mod:`wtopo.kernels.marching_cubes`):

* pass 0 reads every value once for each chunk's min and max, so pass 1 and 2 skip chunks whose
  2x2 block of columns lies strictly on one side of the level (most of a grid);
* pass 1 classifies the remaining nodes and cells and counts each chunk's vertices and faces;
* two exclusive scans (``wp.utils.array_scan``) give every chunk its output ranges, and one host
  sync reads the totals for allocation;
* pass 2 writes vertices and faces.

The three passes are split across CPU threads with :func:`wtopo._bridge.launch_split`; each
thread writes only its own columns' outputs.  The gradient is one explicit per-vertex adjoint
kernel registered with ``tape.record_func``: the extraction itself is never differentiated by Warp.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial

import torch
import warp as wp

from wtopo import _bridge
from wtopo._validate import require_finite, require_tensor, value_checks
from wtopo.kernels import marching_cubes as _k

__all__ = ["marching_cubes"]

#: Smallest ``|b - a|`` the adjoint divides by (field units): an edge whose two values differ by
#: less has its ``1 / (b - a)^2`` derivative clamped so gradients stay below ``1 / GRAD_EPS``.
GRAD_EPS = 1e-7

#: Nodes per z-chunk, the unit of work of one kernel thread.  Chunks whose 2x2 block of node
#: columns lies strictly on one side of the level are skipped after one min/max read; 16 keeps
#: that test fine enough to skip most of a smooth field and threads long enough to amortise it.
CHUNK = 16

# A kernel thread walks a whole node column: a hundred columns are worth a CPU thread of their own.
_MIN_COLUMNS_PER_THREAD = 128

_tables: dict[str, tuple[wp.array, wp.array, wp.array]] = {}


def _grid_spec(level: float, lower: Sequence[float], upper: Sequence[float], shape: Sequence[int],
               device) -> _k.GridSpec:
    """The constant kernel arguments of one extraction; the case tables are uploaded once per device."""
    key = str(device)
    if key not in _tables:
        _tables[key] = (
            wp.array(_k.TRI_RANGE, dtype=wp.int32, device=device),
            wp.array(_k.TRI_EDGES, dtype=wp.int32, device=device),
            wp.array(_k.EDGE_TABLE, dtype=wp.int32, device=device),
        )
    grid = _k.GridSpec()
    grid.level = level
    grid.lower = wp.vec3d(*lower)
    grid.spacing = wp.vec3d(*[(u - a) / (n - 1) for a, u, n in zip(lower, upper, shape)])
    grid.grad_eps = GRAD_EPS
    grid.chunk = CHUNK
    grid.nchunks = -(-(shape[2] - 1) // CHUNK)
    grid.tri_range, grid.tri_edges, grid.edges = _tables[key]
    return grid


def _point(name: str, value) -> tuple[float, float, float]:
    try:
        vals = tuple(float(v) for v in value)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of 3 numbers, got {value!r}") from None
    if len(vals) != 3:
        raise ValueError(f"{name} must have 3 entries, got {len(vals)} ({value!r})")
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return vals


def _require_finite_field(field: torch.Tensor) -> None:
    # A sum is non-finite when any term is (NaN and inf propagate; overflow of huge finite values
    # only sends us to the exact check).  On CPU numpy's single-threaded SIMD sum avoids torch's
    # thread pool, which stalls for tens of ms when the cores are oversubscribed.
    if not value_checks():
        return
    t = field.detach()
    total = t.numpy().sum() if t.device.type == "cpu" else t.sum().item()  # host sync: validation
    if not math.isfinite(float(total)):
        require_finite("field", t)


def _cancel_folded_faces(faces: torch.Tensor, kinds: torch.Tensor) -> wp.array:
    """Drop faces that appear in both orientations (zero-volume folds through node vertices).

    Only faces touching a node vertex (a node exactly on the level) can coincide across cells.
    Faces with the same three vertices cancel by orientation: a group with net orientation 0 is
    dropped, otherwise one face of the winning orientation is kept.
    """
    f = faces.long()
    cand = torch.nonzero((kinds.long()[f] == int(_k.KIND_NODE)).any(dim=1)).squeeze(1)
    sub = f[cand]
    srt, perm = sub.sort(dim=1)
    sign = torch.where(perm[:, 1] == (perm[:, 0] + 1) % 3, 1, -1)  # +1: an even (cyclic) permutation
    _, inv = torch.unique(srt, dim=0, return_inverse=True)
    net = torch.zeros(int(inv.max()) + 1 if inv.numel() else 0, dtype=torch.long, device=f.device)
    net.index_add_(0, inv, sign)
    ok = (net[inv] != 0) & (sign == torch.sign(net[inv]))
    first = torch.full_like(net, cand.numel())
    first.scatter_reduce_(0, inv[ok], torch.nonzero(ok).squeeze(1), reduce="amin")
    keep = torch.ones(f.shape[0], dtype=torch.bool, device=f.device)
    keep[cand] = False
    keep[cand[first[first < cand.numel()]]] = True
    return wp.from_torch(faces[keep].contiguous())


def _run(level: float, lower: Sequence[float], upper: Sequence[float], field: wp.array):
    device = field.device
    nx, ny, nz = field.shape
    scalar = field.dtype
    vec = wp.vec3d if scalar == wp.float64 else wp.vec3
    grid = _grid_spec(level, lower, upper, field.shape, device)
    nchunks = grid.nchunks
    ncols = nx * ny
    values = field.flatten()  # flat view: the column walks index it directly
    nslots = nx * ny * nchunks  # per (column, chunk) results

    chunk_min = wp.empty(nslots, dtype=scalar, device=device)
    chunk_max = wp.empty(nslots, dtype=scalar, device=device)
    _bridge.launch_split(_k.measure_chunks_kernel, ncols, [grid, field, values], [chunk_min, chunk_max],
                         device=device, min_chunk=_MIN_COLUMNS_PER_THREAD)
    # Written only in chunks pass 1 finds active (``chunk_active``): no zero fill, and the pages of
    # skipped chunks are never touched.
    node_mask = wp.empty((nx, ny, nz), dtype=wp.uint8, device=device)
    cell_case = wp.empty((nx - 1, ny - 1, nz - 1), dtype=wp.uint8, device=device)
    chunk_active = wp.empty(nslots, dtype=wp.uint8, device=device)
    chunk_verts = wp.empty(nslots, dtype=wp.int32, device=device)
    chunk_faces = wp.empty(nslots, dtype=wp.int32, device=device)
    _bridge.launch_split(_k.count_chunks_kernel, ncols,
                         [grid, field, values, chunk_min, chunk_max],
                         [node_mask, cell_case, chunk_active, chunk_verts, chunk_faces], device=device,
                         min_chunk=_MIN_COLUMNS_PER_THREAD)

    vert_start = wp.empty(nslots, dtype=wp.int32, device=device)
    face_start = wp.empty(nslots, dtype=wp.int32, device=device)
    wp.utils.array_scan(chunk_verts, vert_start, inclusive=False)
    wp.utils.array_scan(chunk_faces, face_start, inclusive=False)
    # host sync: output sizes for allocation (last exclusive start + last count)
    tails = (vert_start, chunk_verts, face_start, chunk_faces)
    if device.is_cpu:
        tail = [int(a[-1:].numpy()[0]) for a in tails]
    else:  # one device-to-host copy (one sync) instead of four
        tail = torch.stack([wp.to_torch(a)[-1] for a in tails]).tolist()
    n_verts, n_faces = tail[0] + tail[1], tail[2] + tail[3]

    verts = wp.empty(n_verts, dtype=vec, device=device, requires_grad=_bridge.active_tape() is not None)
    faces = wp.empty((n_faces, 3), dtype=wp.int32, device=device)
    if n_verts == 0:
        return verts, faces
    vert_node = wp.empty(n_verts, dtype=wp.int32, device=device)
    vert_kind = wp.empty(n_verts, dtype=wp.uint8, device=device)
    _bridge.launch_split(_k.write_chunks_kernel, ncols,
                         [grid, field, node_mask, cell_case, chunk_active, chunk_verts, chunk_faces, vert_start,
                          face_start],
                         [verts, vert_node, vert_kind, faces], device=device, min_chunk=_MIN_COLUMNS_PER_THREAD)

    if n_faces:
        # host sync: look for node vertices (nodes exactly on the level); numpy on CPU, as above
        kinds = vert_kind.numpy() if device.is_cpu else wp.to_torch(vert_kind)
        if bool((kinds == int(_k.KIND_NODE)).any()):
            faces = _cancel_folded_faces(wp.to_torch(faces), wp.to_torch(vert_kind))

    tape = _bridge.active_tape()
    if field.requires_grad and tape is not None:

        def backward():
            # One launch: several vertices scatter into the same node, and Warp's CPU atomics are
            # only atomic within a launch.
            _bridge.launch(_k.scatter_vertex_adjoint_kernel, dim=n_verts,
                      inputs=[field, grid, vert_node, vert_kind, verts.grad], outputs=[field.grad],
                      device=device, record_tape=False)

        tape.record_func(backward, [verts, field])
    return verts, faces


def marching_cubes(field: torch.Tensor, level: float = 0.0, *, lower: Sequence[float] = (0.0, 0.0, 0.0),
                   upper: Sequence[float] = (1.0, 1.0, 1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Extract the ``level`` isosurface of a scalar grid as a welded triangle mesh.

    Inside is ``field < level``; a node exactly equal to ``level`` counts as outside.  Faces are
    wound so their normals (right-hand rule) point outwards, towards increasing ``field``.

    Args:
        field: scalar samples, shape ``[X, Y, Z]`` with every size >= 2, float32 or float64, finite,
            on CPU or CUDA.  Node ``(i, j, k)`` sits at ``lower + (i, j, k) * (upper - lower) /
            (shape - 1)``; sizes may differ per axis.  Differentiable.
        level: iso value, in field units.  Not differentiable.
        lower: position of node ``(0, 0, 0)`` (3 numbers, length units).
        upper: position of node ``(X-1, Y-1, Z-1)``; ``upper > lower`` on every axis.

    Returns:
        ``(verts, faces)``. ``verts``: shape ``[V, 3]``, ``field``'s dtype and device, in the frame
        of ``lower``/``upper``; one vertex per crossed grid edge, shared by every face using it,
        placed at ``t = (level - a) / (b - a)`` along the edge.  Differentiable w.r.t. ``field``
        through ``t``; where ``|b - a| < GRAD_EPS`` (1e-7) the ``1 / (b - a)^2`` factor is clamped
        (CLAMP: finite forward and backward).  ``faces``: shape ``[F, 3]``, int32, indices into
        ``verts``; discrete, never carries a gradient (marked non-differentiable).  A field with
        no crossing (entirely above, below or equal to ``level``) gives ``[0, 3]`` outputs and a
        zero gradient.

    Raises:
        TypeError: ``field`` is not a float32/float64 tensor, or ``level``/``lower``/``upper`` are
            not numbers.
        ValueError: ``field`` is not 3-D, has a size < 2 or a non-finite value; ``level`` is not
            finite; ``upper <= lower`` on some axis.

    Limitations:
        The grid boundary is not closed: a surface that leaves the grid is cut open along the
        boundary nodes (cells exist only between nodes), and the boundary layer of cells is kept.
        Pad the field with an outside value (e.g. ``torch.nn.functional.pad(f, (1,) * 6,
        value=big)``) to close it.  Ambiguous faces are resolved by the fixed case table
        (Lorensen-Cline / Bourke), not by the asymptotic decider of skimage's Lewiner variant, so
        face counts match skimage except in ambiguous cells.  A node exactly on ``level`` becomes
        one vertex shared by all crossed edges meeting in it (faces collapsed by it are dropped);
        its gradient is the mean of those edges' one-sided derivatives, and a node on the level
        enclosed by inside nodes leaves one vertex no face uses.

    References:
        W. E. Lorensen, H. E. Cline, "Marching cubes: a high resolution 3D surface construction
        algorithm", SIGGRAPH 1987.  P. Bourke, "Polygonising a scalar field", 1994 (case table).
    """
    require_tensor("field", field, ndim=3)
    if min(field.shape) < 2:
        raise ValueError(f"field must have every size >= 2 (2^3 is the smallest grid), got shape {list(field.shape)}")
    if field.numel() >= 2**31:
        raise ValueError(f"field must have fewer than 2^31 nodes (int32 indices), got {field.numel()}")
    if isinstance(level, (torch.Tensor, bool)) or not isinstance(level, (int, float)):
        raise TypeError(f"level must be a Python number, got {type(level).__name__}")
    if not math.isfinite(level):
        raise ValueError(f"level must be finite, got {level!r}")
    lo = _point("lower", lower)
    hi = _point("upper", upper)
    if any(h <= a for a, h in zip(lo, hi)):
        raise ValueError(f"upper must exceed lower on every axis, got lower={lo}, upper={hi}")
    _require_finite_field(field)
    op = _bridge.WarpOp("marching_cubes", partial(_run, float(level), lo, hi), (_bridge.float_dtype(field),),
                        (True,), (True, False))
    verts, faces = _bridge.apply(op, field)
    return verts, faces
