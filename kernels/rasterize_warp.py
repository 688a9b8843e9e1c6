# SPDX-License-Identifier: Apache-2.0
"""Warp-cooperative helpers of the rasterizer's CUDA pixel kernels (``kernels/rasterize.py``).

With ``coop`` (CUDA launches), the 32 pixels of a warp walk their tile's list in step and the helpers
act on the whole warp: a per-surfel sum over the warp and one atomic add by lane 0 instead of one per
pixel (the pixels of a tile all hit the same surfels, so per-pixel atomics serialise). Without it
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
        auto s = v;
        for (int o = 16; o > 0; o >>= 1) s += __shfl_down_sync(0xffffffffu, s, o);
        if ((threadIdx.x & 31) == 0) wp::atomic_add(dest, w, i, s);
        return;
    }
#endif
    if (own) wp::atomic_add(dest, w, i, v);
""")
def warp_add_scalar(dest: wp.array2d[Any], w: int, i: int, v: Any, own: bool, coop: int):
    """``dest[w, i] += v`` summed over the warp by lane 0 (``coop``: ``v`` is 0 on lanes without ``own``),
    else added where ``own``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    if (coop) {
        auto s = v;
        for (unsigned c = 0; c < sizeof(v) / sizeof(v[0]); ++c) {
            for (int o = 16; o > 0; o >>= 1) s[c] += __shfl_down_sync(0xffffffffu, s[c], o);
        }
        if ((threadIdx.x & 31) == 0) wp::atomic_add(dest, w, i, s);
        return;
    }
#endif
    if (own) wp::atomic_add(dest, w, i, v);
""")
def warp_add_vec(dest: wp.array2d[Any], w: int, i: int, v: Any, own: bool, coop: int):
    """:func:`warp_add_scalar` for a vector ``v``."""
    ...
