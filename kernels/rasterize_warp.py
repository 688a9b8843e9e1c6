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
def fetch_batch(ids: wp.array[wp.int32], k: int, step: int, nb: int, lane: int, geo: wp.array[Any],
                opacity: wp.array[Any], color: wp.array[Any], nrm_face: wp.array[Any]):
    """Lane ``j < nb`` reads ``ids[k + j * step]`` and prefetches that surfel's records; returns the id.

    The list is walked one surfel at a time, each step a chain of dependent loads (id, record, then
    opacity, colour, normal) that the warp waits for; fetching the next ``nb`` ids with one load per
    lane and prefetching their records overlaps those latencies (the records of 1M surfels, 64 MB in
    float32, do not fit the L2 cache).
    """
    mine = int(0)
    if lane < nb:
        mine = int(ids[k + lane * step])
        prefetch(geo, mine)
        prefetch(opacity, mine)
        prefetch(color, mine)
        prefetch(nrm_face, mine)
    return mine


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
