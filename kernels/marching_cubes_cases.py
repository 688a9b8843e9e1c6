# SPDX-License-Identifier: Apache-2.0
"""Marching-cubes case tables and the per-cell case helpers of the passes in :mod:`.marching_cubes`.

The triangle table (per case code, its triangles as cell edges), the edge table, the node mask bits,
:class:`GridSpec` (the constant arguments of every pass) and the ``@wp.func`` helpers that classify
nodes and cells: inside bits, node masks under the tie rule, and which triangles of a cell with
corners exactly on the level are kept. Corner and edge numbering as in :mod:`.marching_cubes`.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


# Per case code, its triangles as hexadecimal edge numbers, three per triangle.  This is Paul
# Bourke's public-domain table (the one Warp's ``MC_TRI_LOCAL_INDICES`` also holds) with each
# triangle's winding reversed: with bit = inside, the reversed order makes normals point from the
# inside corners to the outside ones, i.e. towards increasing field.  The table separates inside
# corners on ambiguous faces consistently in both cells sharing the face, so the mesh has no cracks.
TRIANGLE_TABLE = (
    "", "038", "091", "138918", "1a2", "0381a2", "9a2092", "23828aa89", "32b", "02b80b", "1092b3", "12b1b99b8",
    "31ab3a", "01a0a88ab", "30939bb9a", "9a8ab8", "487", "403743", "091874", "491417713", "1a2874", "3743401a2",
    "9a2920874", "29a279237749", "87432b", "b74b42240", "9108742b3", "4b79b492b912", "31a3ab748", "1ab1b414074b",
    "4879b09abb30", "4b749b9ab", "945", "945038", "045105", "845853351", "1a2945", "3801a2459", "5a2524420",
    "25a352345384", "9452b3", "02b0b8459", "0450512b3", "2512852b8458", "ab3a31945", "45901881a8ab", "5045b05abb30",
    "5845a8ab8", "987597", "903935537", "087071175", "135375", "987975a21", "a21905503537", "820852875a25",
    "25a235375", "75979832b", "9759279022b7", "2b3081187175", "b12b71751", "985875a31ab3", "50759070b1a0b0a",
    "b0ab30a05870507", "b5a75b", "a56", "03856a", "91056a", "13818956a", "156216", "156162380", "956960062",
    "589528562382", "2b3a56", "b80b02a56", "0912b356a", "56a12992b9b8", "6b3635531", "0b805b01556b", "36b063056095",
    "6956b9b89", "56a487", "4034376a5", "10956a874", "a56179137749", "621615487", "152562340374", "874950056062",
    "793749392569296", "32b748a56", "56a4274022b7", "0914872b356a", "91292b9b474b56a", "87435b31556b",
    "5b156b1b074b0b4", "095056063b36874", "6956b949779b", "a946a4", "46a4a9038", "a10a06604", "8138618466a1",
    "194142246", "380192294246", "042462", "823842462", "a94a46b32", "0282b84a946a", "32b0610466a1",
    "6146a14182b181b", "946963931b36", "81b801b16941614", "36b306046", "684b86", "76a7a88a9", "03707a0a96a7",
    "a7617a187108", "a76a17137", "162186198876", "296219697039793", "708760620", "723627", "2b3a86a98876",
    "2702b70796a797a", "10818717a6a72b3", "b12b71a16617", "869876961b36163", "019b76", "70876030bb06", "76b", "7b6",
    "380b67", "091b67", "891813b67", "a2167b", "1a238067b", "20929a67b", "67b23aa38a89", "732672", "780706602",
    "267273091", "126168189867", "a67a71173", "a671a7178180", "0730a709a67a", "7a678a89a", "648b68", "3b6360064",
    "8b6864910", "964936913b63", "64868b21a", "1a23b00b6064", "48b4b609229a", "a39a23934b63436", "832824426",
    "024426", "109243264483", "149124264", "83181686461a", "a01a60640", "43648363a093a39", "a4964a", "4597b6",
    "038459b67", "5105047b6", "b67843345351", "945a217b6", "67b1a2038459", "7b65a44a2420", "384345352a25b67",
    "732726594", "945068026678", "326367105504", "682678281458185", "945a61167173", "1a6167170807945",
    "4a045a0a367a3a7", "7a678a5a44a8", "65969bb98", "3b6036065059", "08b0b50515b6", "63b653513", "1a29b598bb65",
    "03b0b60695961a2", "b58b65850a25052", "63b65323aa35", "598582526328", "965906026", "185108586328682", "165261",
    "1631a6368596869", "a01a60905506", "0835a6", "a65", "ba57b5", "ba5b57803", "57b5ba109", "a57a7b918813",
    "b21b17715", "0381721577b2", "95797292027b", "7257b2529382928", "2a5253357", "802825857a52", "91053a57332a",
    "928912827a52725", "153357", "078017157", "930953573", "978579", "54858aa8b", "54050b5bab03", "0918a48baa54",
    "a4ba54b43914341", "21525828b485", "0b403b4b521b5b1", "05209525b485b58", "95423b", "2a5325354348", "52a542402",
    "32a3a5358485091", "52a542129924", "854835315", "054150", "854835950053", "954", "47b4b99ba", "03847997b9ba",
    "1ba14b1047b4", "34138414a7b4a4b", "47b94b9b2921", "94797b9b121b038", "b47b24204", "b47b24843342",
    "2a9297273794", "97a947a72807270", "3a732a7a410a4a0", "12a847", "419471731", "419471018817", "430734", "478",
    "98aa8b", "3903b9ba9", "0a108a8ba", "3a1ba3", "1b219b98b", "3903b919229b", "0b28b0", "3b2", "2832a8a98",
    "92a029", "2832a808118a", "12a", "183981", "019", "083", "",
)

EDGE_CORNERS = ((0, 1), (1, 2), (3, 2), (0, 3), (4, 5), (5, 6), (7, 6), (4, 7), (0, 4), (1, 5), (2, 6), (3, 7))
EDGE_AXIS = (0, 1, 0, 1, 0, 1, 0, 1, 2, 2, 2, 2)


def _flatten(table):
    ranges, edges = [0], []
    for row in table:
        edges.extend(int(ch, 16) for ch in row)
        ranges.append(len(edges))
    return tuple(ranges), tuple(edges)


#: ``TRI_EDGES[TRI_RANGE[c]:TRI_RANGE[c + 1]]`` are the edges of case ``c``'s triangles.
TRI_RANGE, TRI_EDGES = _flatten(TRIANGLE_TABLE)
#: Rows ``(lower corner, upper corner, axis)`` per edge, the kernels' ``edges`` table.
EDGE_TABLE = tuple((a, b, ax) for (a, b), ax in zip(EDGE_CORNERS, EDGE_AXIS))

# Node mask bits (``node_mask``, one byte per node).  The vertices a node owns are stored in bit
# order: its node vertex first, then its x, y, z edge vertices.
NODE_VERTEX = wp.constant(1)  # node value == level and some 6-neighbour is inside: one vertex on the node
EDGE_X = wp.constant(2)  # edge to (i+1, j, k) crossed, its outside end strictly above level
EDGE_Y = wp.constant(4)
EDGE_Z = wp.constant(8)
ON_LEVEL = wp.constant(16)  # node value == level exactly (outside by the tie rule)
KIND_NODE = wp.constant(3)  # vert_kind of a node vertex; 0, 1, 2 = edge vertex along that axis


@wp.struct
class GridSpec:
    """Constant arguments of every pass of one extraction (built by ``wtopo.marching_cubes._grid_spec``).

    Lengths and values are held in float64 and rounded to the field's dtype where a kernel reads
    them (:func:`level_of`; the same single rounding as passing them in that dtype).

    Attributes:
        level: iso value [field units].
        lower: position of node ``(0, 0, 0)`` [length units].
        spacing: distance between neighbouring nodes along each axis [length units].
        grad_eps: smallest ``|b - a|`` the adjoint divides by [field units].
        chunk: nodes per z-chunk (the unit of work of a kernel thread).
        nchunks: z-chunks per node column.
        tri_range: ``TRI_RANGE``, int32 ``[257]``.
        tri_edges: ``TRI_EDGES``, int32.
        edges: ``EDGE_TABLE``, int32 ``[12, 3]``: lower corner, upper corner, axis of each cell edge.
    """

    level: wp.float64
    lower: wp.vec3d
    spacing: wp.vec3d
    grad_eps: wp.float64
    chunk: int
    nchunks: int
    tri_range: wp.array[wp.int32]
    tri_edges: wp.array[wp.int32]
    edges: wp.array2d[wp.int32]


@wp.func
def level_of(grid: GridSpec, v: Any):
    """The iso value in the dtype of the field value ``v``."""
    return type(v)(grid.level)


@wp.func
def popcount4(m: int):
    """Number of vertices a node owns: set bits among its four low mask bits."""
    return (m & 1) + ((m >> 1) & 1) + ((m >> 2) & 1) + ((m >> 3) & 1)


@wp.func
def inside_bit(v: Any, level: Any):
    """1 when ``v`` is inside (``v < level``); a value equal to the level counts as outside."""
    return wp.where(v < level, 1, 0)


@wp.func
def layer_bits(v0: Any, v1: Any, v2: Any, v3: Any, level: Any):
    """Inside bits of the four node columns of one layer, in corner order 0..3."""
    return inside_bit(v0, level) | (inside_bit(v1, level) << 1) | (inside_bit(v2, level) << 2) | (
        inside_bit(v3, level) << 3)


@wp.func
def layer_eq(v0: Any, v1: Any, v2: Any, v3: Any, level: Any):
    """Bits of the four node columns of one layer whose value equals the level exactly."""
    return wp.where(v0 == level, 1, 0) | wp.where(v1 == level, 2, 0) | wp.where(v2 == level, 4, 0) | wp.where(
        v3 == level, 8, 0)


@wp.func
def inside_neighbours(field: wp.array3d[Any], level: Any, i: int, j: int, k: int):
    """Number of the 6 grid neighbours of node ``(i, j, k)`` that are inside."""
    n = int(0)
    if i > 0:
        n += inside_bit(field[i - 1, j, k], level)
    if i + 1 < field.shape[0]:
        n += inside_bit(field[i + 1, j, k], level)
    if j > 0:
        n += inside_bit(field[i, j - 1, k], level)
    if j + 1 < field.shape[1]:
        n += inside_bit(field[i, j + 1, k], level)
    if k > 0:
        n += inside_bit(field[i, j, k - 1], level)
    if k + 1 < field.shape[2]:
        n += inside_bit(field[i, j, k + 1], level)
    return n


@wp.func
def strict_crossing(v: Any, w: Any, level: Any):
    """1 when the edge ``v``-``w`` is crossed and neither end lies exactly on the level."""
    return wp.where(inside_bit(v, level) != inside_bit(w, level) and v != level and w != level, 1, 0)


@wp.func
def node_mask_of(field: wp.array3d[Any], level: Any, i: int, j: int, k: int, v: Any, vx: Any, vy: Any, vz: Any,
                 hx: int, hy: int, hz: int):
    """Mask bits of node ``(i, j, k)`` of value ``v`` whose +x/+y/+z neighbours hold ``vx, vy, vz``.

    ``hx, hy, hz`` are 1 where that neighbour exists.  A node exactly on the level owns no edge
    vertex: every crossed edge ending in it shares its single node vertex instead (tie rule), so
    coincident vertices and the zero-area faces between them never arise.
    """
    m = int(0)
    if v == level:
        m = ON_LEVEL
        if inside_neighbours(field, level, i, j, k) > 0:
            m = m | NODE_VERTEX
    else:
        m = wp.where(hx * strict_crossing(v, vx, level) != 0, EDGE_X, 0)
        m = m | wp.where(hy * strict_crossing(v, vy, level) != 0, EDGE_Y, 0)
        m = m | wp.where(hz * strict_crossing(v, vz, level) != 0, EDGE_Z, 0)
    return m


@wp.func
def edge_key(case: int, eqbits: int, e: int, edges: wp.array2d[wp.int32]):
    """Cell-local identity of the vertex on crossed edge ``e``: ``12 + corner`` for a node vertex, else ``e``."""
    c0 = edges[e, 0]
    out = wp.where(((case >> c0) & 1) == 0, c0, edges[e, 1])
    return wp.where(((eqbits >> out) & 1) != 0, 12 + out, e)


vec15i = wp.types.vector(length=15, dtype=wp.int32)


@wp.func
def same_triangle(keys: vec15i, t: int, u: int):
    """Whether triangles ``t`` and ``u`` (distinct vertices each) use the same three vertices."""
    hits = int(0)
    for a in range(3):
        ka = keys[3 * t + a]
        if ka == keys[3 * u] or ka == keys[3 * u + 1] or ka == keys[3 * u + 2]:
            hits += 1
    return hits == 3


@wp.func
def kept_triangles(case: int, eqbits: int, grid: GridSpec):
    """Bit ``t`` set: keep triangle ``t`` of a cell with corners exactly on the level (``eqbits``).

    Node vertices merge the vertices of all crossed edges ending in one corner, so a triangle can
    collapse (two equal vertices: zero area) and two triangles of the cell can become one face
    traversed both ways (a zero-volume fold).  Both kinds are dropped; dropping a pair of opposite
    copies leaves every edge's use count even.  Pass 1 counts and pass 2 writes with this one rule.
    """
    r0 = grid.tri_range[case]
    n = (grid.tri_range[case + 1] - r0) // 3
    keys = vec15i()
    keep = int(0)
    for t in range(n):
        ka = edge_key(case, eqbits, grid.tri_edges[r0 + 3 * t], grid.edges)
        kb = edge_key(case, eqbits, grid.tri_edges[r0 + 3 * t + 1], grid.edges)
        kc = edge_key(case, eqbits, grid.tri_edges[r0 + 3 * t + 2], grid.edges)
        keys[3 * t] = ka
        keys[3 * t + 1] = kb
        keys[3 * t + 2] = kc
        if ka != kb and kb != kc and ka != kc:
            keep = keep | (1 << t)
    for t in range(n):
        for u in range(t + 1, n):
            if ((keep >> t) & 1) != 0 and ((keep >> u) & 1) != 0 and same_triangle(keys, t, u):
                keep = keep & ~((1 << t) | (1 << u))
    return keep


@wp.func
def popcount8(m: int):
    """Set bits of a byte."""
    return popcount4(m) + popcount4(m >> 4)


@wp.func
def chunk_bounds(c: int, chunk: int, nz: int):
    """Cells ``[k0, k1)`` of z-chunk ``c``; its nodes are ``[k0, k1)`` plus node ``nz - 1`` in the last chunk."""
    k0 = c * chunk
    return k0, wp.min(k0 + chunk, nz - 1)
