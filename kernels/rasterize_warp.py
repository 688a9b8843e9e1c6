# SPDX-License-Identifier: Apache-2.0
"""Warp-cooperative helpers of the rasterizer's CUDA pixel kernels (``kernels/rasterize.py``).

With ``coop`` (CUDA launches), the 32 pixels of a warp walk their tile's list in step and the helpers
act on the whole warp: a surfel's sums over the warp (a ballot for the visibility count, a transposed
shuffle reduction for the 22 gradient values) and one atomic add per value instead of one per pixel (the
pixels of a tile all hit the same surfels, so per-pixel atomics serialise). Without it
(CPU, or CUDA for comparison) each acts on its own pixel. Native code: the warp intrinsics exist only
in the CUDA build; the C++ build (CPU) is the per-pixel form.

Contract of a ``coop`` launch: a multiple of 32 threads, the lanes of a warp in one tile (tiles of
>= 64 pixels in tile-major order, ``rasterize.pixel_tile_coords``), and every lane calling the same helpers
in the same order (warp-uniform control flow around each call).

The kernels call them through ``coop`` and ``batch`` arguments (``wtopo.rasterize._run``:
``COOPERATIVE_WARPS``, ``PREFETCH_BATCH``).
"""

from typing import Any

import warp as wp


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) {
        int m = x;
        for (int o = 16; o > 0; o >>= 1) m = max(m, __shfl_xor_sync(0xffffffffu, m, o));
        return m;
    }
#endif
    return x;
""")
def warp_max(x: int, coop: int) -> int:
    """Maximum of ``x`` over the warp (``coop``) or ``x``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) return __any_sync(0xffffffffu, b) != 0;
#endif
    return b;
""")
def warp_any(b: bool, coop: int) -> bool:
    """Whether ``b`` holds on any lane of the warp (``coop``) or ``b``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) return threadIdx.x & 31;
#endif
    return 0;
""")
def lane_id(coop: int) -> int:
    """Lane of this thread in its warp (``coop``) or 0."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) return __shfl_sync(0xffffffffu, x, src);
#endif
    return x;
""")
def warp_bcast(x: int, src: int, coop: int) -> int:
    """``x`` of lane ``src`` (``coop``) or ``x``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    asm volatile("prefetch.global.L1 [%0];" :: "l"(wp::address(a, i)));
#else
    (void)a;
    (void)i;
#endif
""")
def prefetch(a: wp.array[Any], i: int):
    """Start loading ``a[i]`` into the L1 cache (CUDA; nothing on CPU)."""
    ...


@wp.func
def fetch_batch(ids: wp.array[wp.int32], k: int, step: int, nb: int, lane: int, color: wp.array[Any],
                nrm_face: wp.array[Any]):
    """Lane ``j < nb`` reads ``ids[k + j * step]`` and prefetches that surfel's colour and facing normal; returns
    the id (:func:`stage_batch` then copies the batch's records into shared memory).

    The list is walked one surfel at a time, each step a chain of dependent loads (id, record, then
    opacity, colour, normal) that the warp waits for; fetching the next ``nb`` ids with one load per
    lane overlaps those latencies (the records of 1M surfels, 64 MB in float32, do not fit the L2 cache).
    """
    mine = int(0)
    if lane < nb:
        mine = int(ids[k + lane * step])
        prefetch(color, mine)
        prefetch(nrm_face, mine)
    return mine


# -- per-warp staging of a batch's records in shared memory (CUDA) ------------------------------------------------
# The kernels read each SurfelRecord as four 4-vectors (``geo4``, a [N, 4] view of the records: U, V, n and auv, m2,
# zc and cutoff packed in field order). A slot of the staging slab holds one surfel's four quads and its opacity,
# padded to 16 bytes; a block (256 threads, the launches' default) has 8 warps of 32 slots. Lane j of a warp copies
# surfel j of the batch into its slot with 16-byte loads, then at each step every lane reads slot j of its warp
# (one address: a broadcast) instead of the record's scalar loads from global memory and their address arithmetic.
WARPS_PER_BLOCK = 8
_SLOT = "(4 * sizeof(geo4.data[0]) + 16)"  # bytes of one slot: the record, then the opacity in 16 bytes


_SLAB = f"""
#if defined(__CUDA_ARCH__)
    __shared__ __align__(16) unsigned char slab[{WARPS_PER_BLOCK} * 32 * (16 * sizeof(like) + 16)];
    if (blockDim.x > {WARPS_PER_BLOCK} * 32) __trap();  // more warps than slabs: a launch with another block_dim
    return (wp::uint64)slab;
#else
    return 0;
#endif
"""


@wp.func_native(_SLAB)
def staging_slab(like: wp.float32) -> wp.uint64:
    """Address of this block's staging slab, sized for records of ``like``'s float type (CUDA; 0 on the CPU)."""
    ...


@wp.func_native(_SLAB)
def staging_slab(like: wp.float64) -> wp.uint64:  # noqa: F811 - the float64 overload
    """:func:`staging_slab` of float64 records."""
    ...


@wp.func_native(f"""
#if defined(__CUDA_ARCH__)
    // coop: lane l fills slot l of its warp; else each thread (lane 0 of a batch of 1) fills its own slot
    const unsigned slot = coop ? lane : (threadIdx.x & 31);
    unsigned char* dst = reinterpret_cast<unsigned char*>(slab) + ((threadIdx.x >> 5) * 32 + slot) * {_SLOT};
    if (coop) __syncwarp();  // the warp's reads of the previous batch are done
    if (lane < nb) {{
        const int4* src = reinterpret_cast<const int4*>(wp::address(geo4, mine, 0));
        #pragma unroll
        for (int q = 0; q < static_cast<int>(sizeof(geo4.data[0]) / 4); ++q) {{
            reinterpret_cast<int4*>(dst)[q] = __ldg(src + q);
        }}
        auto* op = reinterpret_cast<decltype(opacity.data)>(dst + 4 * sizeof(geo4.data[0]));
        *op = __ldg(wp::address(opacity, mine));
    }}
    if (coop) __syncwarp();
#endif
""")
def stage_batch(slab: wp.uint64, geo4: wp.array2d[Any], opacity: wp.array[Any], mine: int, lane: int, nb: int,
                coop: int):
    """Lane ``lane < nb`` copies surfel ``mine``'s record and opacity into its slot (CUDA; nothing on the CPU).
    ``coop``: warp-uniform, every lane calls it, slot ``lane``; else each thread stages its own surfel (``lane`` 0,
    ``nb`` 1) in a slot of its own."""
    ...


_SLOT_OF = ("(__builtin_assume(__isShared(reinterpret_cast<void*>(slab))), reinterpret_cast<unsigned char*>(slab))"
            " + ((threadIdx.x >> 5) * 32 + (coop ? j : (threadIdx.x & 31))) * " + _SLOT)
_QUAD32 = f"""
#if defined(__CUDA_ARCH__)
    const float4 v = reinterpret_cast<const float4*>({_SLOT_OF})[q];
    return wp::vec4(v.x, v.y, v.z, v.w);
#else
    return wp::index(geo4, i, q);
#endif
"""
_QUAD64 = f"""
#if defined(__CUDA_ARCH__)
    const double2* p = reinterpret_cast<const double2*>({_SLOT_OF}) + 2 * q;
    const double2 a = p[0];
    const double2 b = p[1];
    return wp::vec4d(a.x, a.y, b.x, b.y);
#else
    return wp::index(geo4, i, q);
#endif
"""
_OPACITY = f"""
#if defined(__CUDA_ARCH__)
    return *reinterpret_cast<decltype(opacity.data)>({_SLOT_OF.replace("geo4", "quad")} + 4 * sizeof(quad.data[0]));
#else
    return wp::index(opacity, i);
#endif
"""


@wp.func_native(_QUAD32)
def staged_quad(slab: wp.uint64, geo4: wp.array2d[wp.vec4], i: int, j: int, q: int, coop: int) -> wp.vec4:
    """Quad ``q`` of surfel ``i``'s record: on CUDA from slot ``j`` of this warp (``coop``; else this thread's own
    slot), on the CPU ``geo4[i, q]``."""
    ...


@wp.func_native(_QUAD64)
def staged_quad(slab: wp.uint64, geo4: wp.array2d[wp.vec4d], i: int, j: int, q: int, coop: int) -> wp.vec4d:  # noqa: F811
    """:func:`staged_quad` of float64 records."""
    ...


@wp.func_native(_OPACITY)
def staged_opacity(slab: wp.uint64, quad: wp.array2d[wp.vec4], opacity: wp.array[wp.float32], i: int, j: int,
                   coop: int) -> wp.float32:
    """Surfel ``i``'s opacity, from the slot :func:`staged_quad` reads (CUDA) or ``opacity[i]`` (CPU). ``quad``:
    ``geo4`` (its type sizes the slot)."""
    ...


@wp.func_native(_OPACITY)
def staged_opacity(slab: wp.uint64, quad: wp.array2d[wp.vec4d], opacity: wp.array[wp.float64], i: int, j: int,  # noqa: F811
                   coop: int) -> wp.float64:
    """:func:`staged_opacity` of float64 records."""
    ...


@wp.func
def staged_record(slab: wp.uint64, geo4: wp.array2d[Any], i: int, j: int, coop: int):
    """Surfel ``i``'s record fields ``(U, V, n, auv, m2, zc, cutoff)`` from its four quads (staged, or ``geo4``)."""
    q0 = staged_quad(slab, geo4, i, j, 0, coop)
    q1 = staged_quad(slab, geo4, i, j, 1, coop)
    q2 = staged_quad(slab, geo4, i, j, 2, coop)
    q3 = staged_quad(slab, geo4, i, j, 3, coop)
    return (wp.vector(q0[0], q0[1], q0[2]), wp.vector(q0[3], q1[0], q1[1]), wp.vector(q1[2], q1[3], q2[0]),
            wp.vector(q2[1], q2[2], q2[3]), wp.vector(q3[0], q3[1]), q3[2], q3[3])


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) {
        const unsigned b = __ballot_sync(0xffffffffu, hit);
        if ((threadIdx.x & 31) == 0) wp::atomic_add(dest, w, i, wp::int32(__popc(b)));
        return;
    }
#endif
    if (hit) wp::atomic_add(dest, w, i, wp::int32(1));
""")
def warp_count(dest: wp.array2d[wp.int32], w: int, i: int, hit: bool, coop: int):
    """``dest[w, i] +=`` the number of lanes of the warp with ``hit`` (``coop``: one ballot, one atomic add by
    lane 0), else 1 where ``hit``."""
    ...


# The 22 gradient slots of one surfel in the backward pixel kernel, in the order of warp_add_grads' values:
# colour 0-2, facing normal 3-5, opacity 6, auv 7-9, uax 10-12, vax 13-15, normal 16-18, projected centre 19-20,
# centre depth 21. The CUDA code below maps lane l to slot l.
GRAD_SLOTS = 22


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) {
        // Transposed reduction: at each of the five steps a lane keeps half of its slots and adds its partner's
        // copy of them (one shuffle per kept slot), so the warp's 32 slots take 16 + 8 + 4 + 2 + 1 = 31 shuffles
        // instead of 5 per slot, and lane l ends with the warp's sum of slot l.
        using F = decltype(c_op);
        F v[32] = {c_color[0], c_color[1], c_color[2], c_nf[0], c_nf[1], c_nf[2], c_op,
                   c_auv[0], c_auv[1], c_auv[2], c_uax[0], c_uax[1], c_uax[2], c_vax[0], c_vax[1], c_vax[2],
                   c_nrm[0], c_nrm[1], c_nrm[2], c_m2[0], c_m2[1], c_zc};
        const unsigned lane = threadIdx.x & 31;
#define WTOPO_HALVE(o)                                                            \
        {                                                                         \
            const bool up = (lane & (o)) != 0;                                    \
            _Pragma("unroll") for (int k = 0; k < (o); ++k) {                     \
                const F send = up ? v[k] : v[k + (o)];                            \
                const F keep = up ? v[k + (o)] : v[k];                            \
                v[k] = keep + __shfl_xor_sync(0xffffffffu, send, (o));            \
            }                                                                     \
        }
        WTOPO_HALVE(16) WTOPO_HALVE(8) WTOPO_HALVE(4) WTOPO_HALVE(2) WTOPO_HALVE(1)
#undef WTOPO_HALVE
        const F s = v[0];
        if (lane < 22 && s != F(0)) {
            // one atomic add per lane, all slots in one instruction (no divergent branches: pointer selects)
            F* p = reinterpret_cast<F*>(wp::address(d_color, w, i)) + lane;
            if (lane >= 3) p = reinterpret_cast<F*>(wp::address(d_nrm_face, w, i)) + (lane - 3);
            if (lane >= 6) p = reinterpret_cast<F*>(wp::address(d_opacity, w, i));
            if (lane >= 7) p = reinterpret_cast<F*>(wp::address(d_auv, w, i)) + (lane - 7);
            if (lane >= 10) p = reinterpret_cast<F*>(wp::address(d_uax, w, i)) + (lane - 10);
            if (lane >= 13) p = reinterpret_cast<F*>(wp::address(d_vax, w, i)) + (lane - 13);
            if (lane >= 16) p = reinterpret_cast<F*>(wp::address(d_nrm, w, i)) + (lane - 16);
            if (lane >= 19) p = reinterpret_cast<F*>(wp::address(d_m2, w, i)) + (lane - 19);
            if (lane >= 21) p = reinterpret_cast<F*>(wp::address(d_zc, w, i));
            atomicAdd(p, s);
        }
        return;
    }
#endif
    if (!own) return;
    wp::atomic_add(d_color, w, i, c_color);
    wp::atomic_add(d_nrm_face, w, i, c_nf);
    wp::atomic_add(d_opacity, w, i, c_op);
    if (branch3d) {
        wp::atomic_add(d_auv, w, i, c_auv);
        wp::atomic_add(d_uax, w, i, c_uax);
        wp::atomic_add(d_vax, w, i, c_vax);
        wp::atomic_add(d_nrm, w, i, c_nrm);
    } else {
        wp::atomic_add(d_m2, w, i, c_m2);
        wp::atomic_add(d_zc, w, i, c_zc);
    }
""")
def warp_add_grads(w: int, i: int, c_color: Any, c_nf: Any, c_op: Any, c_auv: Any, c_uax: Any, c_vax: Any,
                   c_nrm: Any, c_m2: Any, c_zc: Any, d_color: wp.array2d[Any], d_nrm_face: wp.array2d[Any],
                   d_opacity: wp.array2d[Any], d_auv: wp.array2d[Any], d_uax: wp.array2d[Any],
                   d_vax: wp.array2d[Any], d_nrm: wp.array2d[Any], d_m2: wp.array2d[Any], d_zc: wp.array2d[Any],
                   own: bool, branch3d: bool, coop: int):
    """Add one surfel's gradient contributions (the ``c_*`` values, in the slots of ``GRAD_SLOTS``) into row ``w``,
    entry ``i`` of the ``d_*`` buffers.

    ``coop``: summed over the warp (lanes without a contribution pass zeros) by a transposed reduction, then one
    atomic add per slot, each by its own lane, only of the sums that are not zero. Else, where ``own``: colour,
    facing normal and opacity always, the 3D branch's terms (``auv``, ``uax``, ``vax``, normal) where
    ``branch3d``, the filter branch's (``m2``, ``zc``) where not.
    """
    ...
