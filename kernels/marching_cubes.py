# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of marching cubes: column count/write passes and the vertex adjoint.

The case tables, :class:`GridSpec` and the per-cell case helpers (inside bits, node masks, kept
triangles) are in :mod:`.marching_cubes_cases`; this module holds the passes.

The extraction is discrete (``enable_backward=False`` for the whole module); the only gradient,
vertex position w.r.t. the field, is the explicit adjoint :func:`scatter_vertex_adjoint_kernel`.

Layout of the work: a *column* is the line of nodes ``(i, j, 0..Z-1)``, cut into z-chunks of
``chunk`` nodes; one kernel thread walks one column upwards, chunk by chunk.  Node ``(i, j, k)`` owns its three
"lower" edges (to ``+x``, ``+y``, ``+z``), so every crossed edge has exactly one owner and
vertices are welded without a hash.  Column ``(i, j)`` also owns the cells whose lowest corner is
``(i, j, k)``.

Corner ``c`` of a cell, bit ``c`` of its case code (set = inside, ``field < level``):
``0 (0,0,0), 1 (1,0,0), 2 (1,1,0), 3 (0,1,0)``, corners 4..7 the same one layer up.  Edge ``e``
joins corners ``EDGE_CORNERS[e]`` (lower corner first) along axis ``EDGE_AXIS[e]``.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .marching_cubes_cases import (
    EDGE_TABLE,
    EDGE_X,
    EDGE_Y,
    EDGE_Z,
    KIND_NODE,
    NODE_VERTEX,
    ON_LEVEL,
    TRI_EDGES,
    TRI_RANGE,
    GridSpec,
    chunk_bounds,
    kept_triangles,
    layer_bits,
    layer_eq,
    level_of,
    node_mask_of,
    popcount4,
    popcount8,
)

wp.set_module_options({"enable_backward": False})

__all__ = ["GridSpec", "TRI_RANGE", "TRI_EDGES", "EDGE_TABLE", "KIND_NODE", "measure_chunks_kernel",
           "count_chunks_kernel", "write_chunks_kernel", "scatter_vertex_adjoint_kernel"]

vec8i = wp.types.vector(length=8, dtype=wp.int32)


@wp.func
def measure_chunk(
    col: int,
    c: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    values: wp.array[Any],
    chunk_min: wp.array[Any],
    chunk_max: wp.array[Any],
):
    """Min and max of z-chunk ``c`` of node column ``col`` over its nodes ``[k0, k1]`` (inclusive).

    A column is the line of nodes ``(i, j, :)``, numbered ``i * Y + j``; per-chunk results are
    stored at ``col * nchunks + c``.
    """
    tid = col * grid.nchunks + c
    k0, k1 = chunk_bounds(c, grid.chunk, field.shape[2])
    base = col * field.shape[2]  # flat index of node (i, j, 0) in ``values``, the flat view of ``field``
    lo = values[base + k0]
    hi = lo
    for k in range(k0 + 1, k1 + 1):
        v = values[base + k]
        lo = wp.min(lo, v)
        hi = wp.max(hi, v)
    chunk_min[tid] = lo
    chunk_max[tid] = hi


@wp.kernel
def measure_chunks_kernel(
    offset: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    values: wp.array[Any],
    chunk_min: wp.array[Any],
    chunk_max: wp.array[Any],
):
    """Pass 0, one thread per node column ``offset + tid``: :func:`measure_chunk` of each of its z-chunks.

    A thread walks a whole column (few threads, each long: per-thread launch cost on CPU is
    comparable to the work of a skipped chunk).
    """
    col = wp.tid() + offset
    for c in range(grid.nchunks):
        measure_chunk(col, c, grid, field, values, chunk_min, chunk_max)


@wp.func
def count_chunk(
    col: int,
    c: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    values: wp.array[Any],
    chunk_min: wp.array[Any],
    chunk_max: wp.array[Any],
    node_mask: wp.array3d[wp.uint8],
    cell_case: wp.array3d[wp.uint8],
    chunk_active: wp.array[wp.uint8],
    chunk_verts: wp.array[wp.int32],
    chunk_faces: wp.array[wp.int32],
):
    """Node masks, cell case codes and counts of z-chunk ``c`` of node column ``col`` (pass 1).

    A chunk whose 2x2 block of node columns lies strictly on one side of the level (from pass 0)
    has no vertex, face or tie: it is flagged inactive in ``chunk_active`` and returns at once,
    leaving its ``node_mask``/``cell_case`` entries unwritten (pass 2 reads them as 0 through the
    flag), so most of a grid costs one sequential read and no memory traffic.  Otherwise every node
    mask and cell case of the chunk is written, walking up the chunk and reusing each layer's four
    values for the next cell.
    """
    nchunks = grid.nchunks
    tid = col * nchunks + c
    level = level_of(grid, chunk_min[tid])
    nx = field.shape[0]
    ny = field.shape[1]
    nz = field.shape[2]
    i = col // ny
    j = col - i * ny
    hx = wp.where(i + 1 < nx, 1, 0)
    hy = wp.where(j + 1 < ny, 1, 0)
    i1 = i + hx
    j1 = j + hy
    c1 = (i1 * ny + j) * nchunks + c
    c2 = (i1 * ny + j1) * nchunks + c
    c3 = (i * ny + j1) * nchunks + c
    lo = wp.min(wp.min(chunk_min[tid], chunk_min[c1]), wp.min(chunk_min[c2], chunk_min[c3]))
    hi = wp.max(wp.max(chunk_max[tid], chunk_max[c1]), wp.max(chunk_max[c2], chunk_max[c3]))
    if lo > level or hi < level:
        chunk_active[tid] = wp.uint8(0)
        chunk_verts[tid] = 0
        chunk_faces[tid] = 0
        return
    chunk_active[tid] = wp.uint8(1)
    cells = hx * hy  # this column also owns a column of cells
    k0, k1 = chunk_bounds(c, grid.chunk, nz)
    # Values of the four node columns (i,j), (i+1,j), (i+1,j+1), (i,j+1) in corner order, at layer k.
    # flat indices (in ``values``, the flat view of ``field``) of node (., ., 0) of the four columns
    p0 = (i * ny + j) * nz
    p1 = (i1 * ny + j) * nz
    p2 = (i1 * ny + j1) * nz
    p3 = (i * ny + j1) * nz
    a0 = values[p0 + k0]
    a1 = values[p1 + k0]
    a2 = values[p2 + k0]
    a3 = values[p3 + k0]
    lay = layer_bits(a0, a1, a2, a3, level)
    eq = layer_eq(a0, a1, a2, a3, level)
    nv = int(0)
    nf = int(0)
    for k in range(k0, k1):
        b0 = values[p0 + k + 1]
        b1 = values[p1 + k + 1]
        b2 = values[p2 + k + 1]
        b3 = values[p3 + k + 1]
        lay_b = layer_bits(b0, b1, b2, b3, level)
        eq_b = layer_eq(b0, b1, b2, b3, level)
        case = lay | (lay_b << 4)
        eqbits = eq | (eq_b << 4)
        m = int(0)
        if eqbits != 0 or (case != 0 and case != 255) or cells == 0:
            m = node_mask_of(field, level, i, j, k, a0, a1, a3, b0, hx, hy, 1)
            nv += popcount4(m)
            if cells != 0:
                if eqbits == 0:
                    nf += (grid.tri_range[case + 1] - grid.tri_range[case]) // 3
                else:
                    nf += popcount8(kept_triangles(case, eqbits, grid))
        node_mask[i, j, k] = wp.uint8(m)
        if cells != 0:
            cell_case[i, j, k] = wp.uint8(case)
        a0 = b0
        a1 = b1
        a2 = b2
        a3 = b3
        lay = lay_b
        eq = eq_b
    if k1 == nz - 1:
        m_top = node_mask_of(field, level, i, j, nz - 1, a0, a1, a3, a0, hx, hy, 0)
        node_mask[i, j, nz - 1] = wp.uint8(m_top)
        nv += popcount4(m_top)
    chunk_verts[tid] = nv
    chunk_faces[tid] = nf


@wp.kernel
def count_chunks_kernel(
    offset: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    values: wp.array[Any],
    chunk_min: wp.array[Any],
    chunk_max: wp.array[Any],
    node_mask: wp.array3d[wp.uint8],
    cell_case: wp.array3d[wp.uint8],
    chunk_active: wp.array[wp.uint8],
    chunk_verts: wp.array[wp.int32],
    chunk_faces: wp.array[wp.int32],
):
    """Pass 1, one thread per node column ``offset + tid``: :func:`count_chunk` of each of its z-chunks.

    A thread walks a whole column (few threads, each long: per-thread launch cost on CPU is
    comparable to the work of a skipped chunk).
    """
    col = wp.tid() + offset
    for c in range(grid.nchunks):
        count_chunk(col, c, grid, field, values, chunk_min, chunk_max, node_mask, cell_case, chunk_active, chunk_verts,
                    chunk_faces)


@wp.func
def vertex_id(case: int, e: int, bases: vec8i, masks: vec8i, edges: wp.array2d[wp.int32]):
    """Global index of the vertex on crossed edge ``e`` of a cell with corner vertex bases ``bases``."""
    c0 = edges[e, 0]
    out = wp.where(((case >> c0) & 1) == 0, c0, edges[e, 1])
    rank = popcount4(masks[c0] & ((2 << edges[e, 2]) - 1))  # owner's vertices stored before this edge's
    return wp.where((masks[out] & ON_LEVEL) != 0, bases[out], bases[c0] + rank)


@wp.func
def write_node_vertices(field: wp.array3d[Any], grid: GridSpec, i: int, j: int, k: int, m: int, base: int,
                        verts: wp.array[Any], vert_node: wp.array[wp.int32], vert_kind: wp.array[wp.uint8]):
    """Write the vertices node ``(i, j, k)`` owns (mask ``m``) from index ``base`` on."""
    v = field[i, j, k]
    level = level_of(grid, v)
    sx = type(v)(grid.spacing[0])
    sy = type(v)(grid.spacing[1])
    sz = type(v)(grid.spacing[2])
    lin = (i * field.shape[1] + j) * field.shape[2] + k
    x = type(v)(grid.lower[0]) + sx * type(v)(i)
    y = type(v)(grid.lower[1]) + sy * type(v)(j)
    z = type(v)(grid.lower[2]) + sz * type(v)(k)
    one = type(v)(1.0)
    zero = type(v)(0.0)
    idx = base
    if (m & NODE_VERTEX) != 0:
        verts[idx] = wp.vector(x, y, z)
        vert_node[idx] = lin
        vert_kind[idx] = wp.uint8(KIND_NODE)
        idx += 1
    if (m & EDGE_X) != 0:
        # t = (level - a) / (b - a) lies in (0, 1]: the ends are strictly on both sides (rounding is
        # monotone); the clamp only guards the degenerate 0/0 a NaN-free field cannot produce.
        t = wp.clamp((level - v) / (field[i + 1, j, k] - v), zero, one)
        verts[idx] = wp.vector(x + sx * t, y, z)
        vert_node[idx] = lin
        vert_kind[idx] = wp.uint8(0)
        idx += 1
    if (m & EDGE_Y) != 0:
        t = wp.clamp((level - v) / (field[i, j + 1, k] - v), zero, one)
        verts[idx] = wp.vector(x, y + sy * t, z)
        vert_node[idx] = lin
        vert_kind[idx] = wp.uint8(1)
        idx += 1
    if (m & EDGE_Z) != 0:
        t = wp.clamp((level - v) / (field[i, j, k + 1] - v), zero, one)
        verts[idx] = wp.vector(x, y, z + sz * t)
        vert_node[idx] = lin
        vert_kind[idx] = wp.uint8(2)


@wp.func
def read_mask(node_mask: wp.array3d[wp.uint8], active: int, i: int, j: int, k: int):
    """Mask of node ``(i, j, k)``, or 0 when its chunk was skipped in pass 1 (entry never written)."""
    m = int(0)
    if active != 0:
        m = int(node_mask[i, j, k])
    return m


@wp.func
def write_chunk(
    col: int,
    c: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    node_mask: wp.array3d[wp.uint8],
    cell_case: wp.array3d[wp.uint8],
    chunk_active: wp.array[wp.uint8],
    chunk_verts: wp.array[wp.int32],
    chunk_faces: wp.array[wp.int32],
    vert_start: wp.array[wp.int32],
    face_start: wp.array[wp.int32],
    verts: wp.array[Any],
    vert_node: wp.array[wp.int32],
    vert_kind: wp.array[wp.uint8],
    faces: wp.array2d[wp.int32],
):
    """Write the vertices and faces of z-chunk ``c`` of node column ``col`` (pass 2).

    ``vert_start``/``face_start`` are exclusive prefix sums of the pass-1 counts in thread order,
    so the vertex base of any node column at the chunk's first layer is one lookup, and bases of
    higher layers are running sums of the node masks: no per-node index array.  Chunks without
    vertices or faces return at once.  Node masks of chunks pass 1 skipped were never written and
    read as 0 (``chunk_active``); the chunk's top layer belongs to the next chunk up.
    """
    nchunks = grid.nchunks
    tid = col * nchunks + c
    if chunk_verts[tid] == 0 and chunk_faces[tid] == 0:
        return
    nx = field.shape[0]
    ny = field.shape[1]
    nz = field.shape[2]
    i = col // ny
    j = col - i * ny
    hx = wp.where(i + 1 < nx, 1, 0)
    hy = wp.where(j + 1 < ny, 1, 0)
    i1 = i + hx
    j1 = j + hy
    cells = hx * hy
    k0, k1 = chunk_bounds(c, grid.chunk, nz)
    s1 = (i1 * ny + j) * nchunks + c
    s2 = (i1 * ny + j1) * nchunks + c
    s3 = (i * ny + j1) * nchunks + c
    base0 = vert_start[tid]
    base1 = vert_start[s1]
    base2 = vert_start[s2]
    base3 = vert_start[s3]
    # activity of the four columns' chunk c, and of the chunk above (holding layer k1) if any
    up = wp.where(c + 1 < nchunks, 1, 0)
    act0 = int(chunk_active[tid])
    act1 = int(chunk_active[s1])
    act2 = int(chunk_active[s2])
    act3 = int(chunk_active[s3])
    top0 = int(chunk_active[tid + up])
    top1 = int(chunk_active[s1 + up])
    top2 = int(chunk_active[s2 + up])
    top3 = int(chunk_active[s3 + up])
    m0 = read_mask(node_mask, act0, i, j, k0)
    m1 = read_mask(node_mask, act1, i1, j, k0)
    m2 = read_mask(node_mask, act2, i1, j1, k0)
    m3 = read_mask(node_mask, act3, i, j1, k0)
    fo = face_start[tid]
    for k in range(k0, k1):
        if (m0 & 15) != 0:
            write_node_vertices(field, grid, i, j, k, m0, base0, verts, vert_node, vert_kind)
        last = k + 1 == k1
        n0 = read_mask(node_mask, wp.where(last, top0, act0), i, j, k + 1)
        n1 = read_mask(node_mask, wp.where(last, top1, act1), i1, j, k + 1)
        n2 = read_mask(node_mask, wp.where(last, top2, act2), i1, j1, k + 1)
        n3 = read_mask(node_mask, wp.where(last, top3, act3), i, j1, k + 1)
        up0 = base0 + popcount4(m0)
        up1 = base1 + popcount4(m1)
        up2 = base2 + popcount4(m2)
        up3 = base3 + popcount4(m3)
        if cells != 0:
            case = int(cell_case[i, j, k])
            r0 = grid.tri_range[case]
            r1 = grid.tri_range[case + 1]
            if r1 > r0:
                bases = vec8i(base0, base1, base2, base3, up0, up1, up2, up3)
                masks = vec8i(m0, m1, m2, m3, n0, n1, n2, n3)
                keep = int(31)
                eqbits = int(0)
                for q in range(8):
                    eqbits = eqbits | wp.where((masks[q] & ON_LEVEL) != 0, 1 << q, 0)
                if eqbits != 0:
                    keep = kept_triangles(case, eqbits, grid)
                for t in range((r1 - r0) // 3):
                    if ((keep >> t) & 1) != 0:
                        r = r0 + 3 * t
                        faces[fo, 0] = vertex_id(case, grid.tri_edges[r], bases, masks, grid.edges)
                        faces[fo, 1] = vertex_id(case, grid.tri_edges[r + 1], bases, masks, grid.edges)
                        faces[fo, 2] = vertex_id(case, grid.tri_edges[r + 2], bases, masks, grid.edges)
                        fo += 1
        base0 = up0
        base1 = up1
        base2 = up2
        base3 = up3
        m0 = n0
        m1 = n1
        m2 = n2
        m3 = n3
    if k1 == nz - 1 and (m0 & 15) != 0:
        write_node_vertices(field, grid, i, j, nz - 1, m0, base0, verts, vert_node, vert_kind)


@wp.kernel
def write_chunks_kernel(
    offset: int,
    grid: GridSpec,
    field: wp.array3d[Any],
    node_mask: wp.array3d[wp.uint8],
    cell_case: wp.array3d[wp.uint8],
    chunk_active: wp.array[wp.uint8],
    chunk_verts: wp.array[wp.int32],
    chunk_faces: wp.array[wp.int32],
    vert_start: wp.array[wp.int32],
    face_start: wp.array[wp.int32],
    verts: wp.array[Any],
    vert_node: wp.array[wp.int32],
    vert_kind: wp.array[wp.uint8],
    faces: wp.array2d[wp.int32],
):
    """Pass 2, one thread per node column ``offset + tid``: :func:`write_chunk` of each of its z-chunks.

    A thread walks a whole column (few threads, each long: per-thread launch cost on CPU is
    comparable to the work of a skipped chunk).
    """
    col = wp.tid() + offset
    for c in range(grid.nchunks):
        write_chunk(col, c, grid, field, node_mask, cell_case, chunk_active, chunk_verts, chunk_faces, vert_start,
                    face_start, verts, vert_node, vert_kind, faces)


@wp.func
def guard(d: Any, eps: Any):
    """``d`` with its magnitude clamped to at least ``eps`` (sign kept): bounds 1/d in the adjoint."""
    return wp.where(wp.abs(d) < eps, wp.where(d < type(d)(0.0), -eps, eps), d)


@wp.kernel
def scatter_vertex_adjoint_kernel(
    field: wp.array3d[Any],
    grid: GridSpec,
    vert_node: wp.array[wp.int32],
    vert_kind: wp.array[wp.uint8],
    adj_verts: wp.array[Any],
    adj_field: wp.array3d[Any],
):
    """Explicit adjoint of the vertex positions w.r.t. the field, one thread per vertex.

    Edge vertex between node values ``a`` (owner) and ``b`` along axis ``d``:
    ``p_d = x_a + spacing_d * t`` with ``t = (level - a) / (b - a)``, so
    ``dt/da = (level - b) / (b - a)^2`` and ``dt/db = (a - level) / (b - a)^2``; ``|b - a|`` is
    clamped to ``eps = grid.grad_eps`` so both stay bounded by ``1 / eps``.  A node vertex (value == level) takes
    the mean of the one-sided derivatives of the crossed edges meeting in it (each moves the
    vertex towards its inside neighbour by ``spacing / (level - f_neighbour)`` per unit of field).
    """
    v = wp.tid()
    ny = field.shape[1]
    nz = field.shape[2]
    lin = vert_node[v]
    kind = int(vert_kind[v])
    i = lin // (ny * nz)
    rem = lin - i * ny * nz
    j = rem // nz
    k = rem - j * nz
    g = adj_verts[v]
    a = field[i, j, k]
    level = level_of(grid, a)
    eps = type(a)(grid.grad_eps)
    spacing = wp.vector(type(a)(grid.spacing[0]), type(a)(grid.spacing[1]), type(a)(grid.spacing[2]))
    if kind != KIND_NODE:
        di = wp.where(kind == 0, 1, 0)
        dj = wp.where(kind == 1, 1, 0)
        dk = wp.where(kind == 2, 1, 0)
        b = field[i + di, j + dj, k + dk]
        d = guard(b - a, eps)
        gt = g[kind] * spacing[kind] / (d * d)
        wp.atomic_add(adj_field, i, j, k, gt * (level - b))
        wp.atomic_add(adj_field, i + di, j + dj, k + dk, gt * (a - level))
    else:
        acc = type(a)(0.0)
        cnt = int(0)
        for q in range(6):
            axis = q // 2
            sgn = 1 - 2 * (q - 2 * axis)  # +1 then -1 along each axis
            ni = i + wp.where(axis == 0, sgn, 0)
            nj = j + wp.where(axis == 1, sgn, 0)
            nk = k + wp.where(axis == 2, sgn, 0)
            if ni >= 0 and ni < field.shape[0] and nj >= 0 and nj < ny and nk >= 0 and nk < nz:
                fm = field[ni, nj, nk]
                if fm < level:
                    acc += type(a)(sgn) * spacing[axis] * g[axis] / guard(a - fm, eps)
                    cnt += 1
        if cnt > 0:
            wp.atomic_add(adj_field, i, j, k, acc / type(a)(cnt))
