# SPDX-License-Identifier: Apache-2.0
"""The differentiable op's Warp launches: per-surfel preparation, per-pixel compositing and the
explicit reverse-traversal adjoint recorded on the tape; on CPU the per-pixel kernels run as tile
chunks spread over worker threads with per-worker gradient buffers summed in a fixed order."""

from __future__ import annotations

import threading

import torch
import warp as wp

from .. import _bridge
from .._profile import section
from ..camera import Camera
from ..kernels import rasterize as _k
from ..kernels import rasterize_backward as _kbwd
from ..kernels import rasterize_binning as _kb
from ..kernels import rasterize_tiles as _kt
from ._binning import _Bins
from ._config import RasterConfig

# CUDA: the 32 pixels of a warp composite in step and sum their per-surfel gradients and visibility
# counts before one atomic add (kernels/rasterize.py, "warp-cooperative helpers"); False restores one
# atomic per pixel (the previous kernels' order of work, kept for comparison in tests and benchmarks).
# CPU launches never use it (one pixel at a time: bit-identical either way).
COOPERATIVE_WARPS = True
# With COOPERATIVE_WARPS: surfels of a tile's list fetched per step of the walk, one id load and L1 prefetch
# of its records per lane (1..32; 1: each surfel's id, then its records, loaded when it is reached).
PREFETCH_BATCH = 32
# CPU: one thread per tile, each surfel visiting only its pixel rectangle (kernels/rasterize_tiles.py); False
# runs the per-pixel kernels as CUDA does (same results bit for bit, kept for comparison in tests and benchmarks).
CPU_TILE_KERNELS = True

# A render that nothing differentiates (no tape) prepares and packs its records in one kernel
# (kernels/rasterize.py, prepare_records_kernel); False: the two kernels of a differentiable render.
FUSED_FORWARD = True

_compiled: set = set()
_compile_lock = threading.Lock()


def _launch_tiles(kernel, n_tiles: int, tile_px: int, inputs: list, outputs: list, *, device, workers: int,
                  tiles_per_chunk: int) -> None:
    """Launch a per-pixel kernel ``(offset, worker, ...)`` over tiles, in chunks spread over ``workers`` threads."""
    if n_tiles <= 0:
        return
    key = (kernel.key, str(device), tuple(getattr(a, "dtype", type(a)) for a in (*inputs, *outputs)))
    if workers <= 1:
        _bridge.launch(kernel, dim=n_tiles * tile_px, inputs=[0, 0, *inputs], outputs=outputs, device=device,
                  record_tape=False)
        return
    chunk = tiles_per_chunk or max(1, n_tiles // (16 * workers))
    n_chunks = -(-n_tiles // chunk)

    def work(w: int) -> None:
        # static interleaved assignment: balanced for spatially clustered cost, and each worker's
        # buffer always sums the same chunks in the same order (bit-identical reruns)
        for c in range(w, n_chunks, workers):
            lo, hi = c * chunk, min(n_tiles, (c + 1) * chunk)
            _bridge.launch(kernel, dim=(hi - lo) * tile_px, inputs=[lo * tile_px, w, *inputs], outputs=outputs,
                      device=device, record_tape=False)

    if key not in _compiled:
        with _compile_lock:  # the first launch compiles: never from two threads at once
            for w in range(workers):  # same chunk-to-worker assignment as the threaded path: same sums
                work(w)
            _compiled.add(key)
        return
    futures = [_bridge._get_pool(workers).submit(work, w) for w in range(workers)]  # noqa: SLF001
    for f in futures:
        f.result()


def _launch_worker_tiles(kernel, n_tiles: int, inputs: list, outputs: list, *, device, workers: int,
                         tiles_per_chunk: int) -> None:
    """Launch a per-tile kernel ``(worker, workers, chunk, ...)`` once per worker thread.

    Worker ``w`` takes the chunks ``w, w + workers, ...`` of ``chunk`` tiles in that order (the tile chunks
    of :func:`_launch_tiles`: the same sums in the same order), as one launch that maps its threads to them
    (``kernels/rasterize_tiles.py``, ``worker_tile``): one launch per worker instead of one per chunk, so the
    workers hardly take the GIL; worker 0 runs on the calling thread.
    """
    if n_tiles <= 0:
        return
    chunk = tiles_per_chunk or max(1, n_tiles // (16 * workers))
    n_chunks = -(-n_tiles // chunk)
    dims = [sum(min(chunk, n_tiles - c * chunk) for c in range(w, n_chunks, workers)) for w in range(workers)]

    def work(w: int) -> None:
        if dims[w]:
            _bridge.launch(kernel, dim=dims[w], inputs=[w, workers, chunk, *inputs], outputs=outputs, device=device,
                      record_tape=False)

    key = (kernel.key, str(device), tuple(getattr(a, "dtype", type(a)) for a in (*inputs, *outputs)))
    if workers <= 1 or key not in _compiled:
        with _compile_lock:  # the first launch compiles: never from two threads at once
            for w in range(workers):
                work(w)
            _compiled.add(key)
        return
    futures = [_bridge._get_pool(workers).submit(work, w) for w in range(1, workers)]  # noqa: SLF001
    work(0)
    for f in futures:
        f.result()


def _num_workers(wdev, n_tiles: int) -> int:
    if not wdev.is_cpu:
        return 1  # CUDA: one launch, real atomics
    return max(1, min(_bridge.cpu_threads(), n_tiles))


def _make_run(bins: _Bins, rays: torch.Tensor, cam_rec, bg_wp, sh_degree: int, camera: Camera, config, wdev, dtype):
    ts = config.tile_size
    tiles_x, tiles_y = -(-camera.width // ts), -(-camera.height // ts)
    n_tiles = tiles_x * tiles_y
    h, w = camera.height, camera.width
    workers = _num_workers(wdev, n_tiles)
    s = wp.float64 if dtype == torch.float64 else wp.float32
    v2, v3, v4 = (wp.vec2d, wp.vec3d, wp.vec4d) if dtype == torch.float64 else (wp.vec2, wp.vec3, wp.vec4)
    rays_wp = _bridge.to_warp(rays, v3)
    coop = int(COOPERATIVE_WARPS and not wdev.is_cpu)
    tiles = bool(CPU_TILE_KERNELS and wdev.is_cpu)
    batch = PREFETCH_BATCH if coop else 1  # a batch is spread over the lanes of a warp

    def run(means, quats, scales, opacities, sh, means2d):
        n = means.shape[0]
        with section("rasterize_forward"):
            tape = _bridge.active_tape()  # None: no gradient can flow (the bridge's no-grad path), none allocated
            grad = tape is not None
            geo = _bridge.empty_struct(n, _k.SURFEL[s], wdev)
            prep_in = [means, quats, scales, sh, cam_rec, sh_degree]
            if not grad and FUSED_FORWARD:
                # nothing differentiates this render: the records, facing normals and colours in one pass
                nrm_face, color = _bridge.empty(n, v3, wdev), _bridge.empty(n, v3, wdev)
                _bridge.launch_split(_k.prepare_records_kernel, n, [*prep_in, bins.cutoff],
                                     [_bridge.quad_view(geo, v4), nrm_face, color], device=wdev)
            else:
                prep = _bridge.empty_group(n, (v3, v3, v3, v3, v3, v2, s, v3), wdev, requires_grad=grad)
                uax, vax, nrm, auv, nrm_face, m2, zc, color = prep
                _bridge.launch_split(_k.prepare_surfels_kernel, n, prep_in, prep, device=wdev)
                _bridge.launch_split(_k.pack_surfels_kernel, n, [uax, vax, nrm, auv, m2, zc, bins.cutoff], [geo],
                                     device=wdev)
            if tape is not None and n > 0:
                # Warp autodiff's adjoint of the preparation (replayed after the pixel adjoint below, which writes
                # the gradients it reads); the camera record gets none (no gradient array)
                def prep_backward():
                    with section("rasterize_backward"):
                        adj = [0, *(a.grad for a in prep_in[:4]), None, 0, *(p.grad for p in prep)]
                        _bridge.launch_adjoint(_k.prepare_surfels_kernel, n, [0, *prep_in, *prep], adj, device=wdev)

                tape.record_func(prep_backward, [a for a in (*prep_in[:4], *prep) if a.grad is not None])
            outs = [_bridge.empty((h, w), t, wdev, requires_grad=grad) for t in (v3, s, s, s, v3, s)]
            rgb, alpha, depth, median, normal, dist = outs
            t_final = _bridge.empty((h, w), s, wdev)
            sums = _bridge.empty((h, w), v3, wdev)
            last = _bridge.empty((h, w), wp.int32, wdev)
            median_idx = _bridge.empty((h, w), wp.int32, wdev)
            visibility = _bridge.empty(n, wp.int32, wdev, zero=True) if workers == 1 else None
            # one worker (CUDA): the kernel counts straight into the output, no per-worker buffer to sum
            vis_w = (visibility.reshape((1, n)) if workers == 1
                     else _bridge.empty((workers, n), wp.int32, wdev, zero=True))
            surf = [geo, nrm_face, color, opacities, bg_wp, ts, tiles_x]
            if tiles:
                done = _bridge.empty((h, w), wp.int32, wdev)
                _launch_worker_tiles(_kt.render_forward_tiles_kernel, n_tiles,
                                     [bins.tile_start, bins.tile_end, bins.ids, bins.prect, rays_wp, cam_rec, *surf],
                                     [*outs, t_final, sums, last, median_idx, done, vis_w], device=wdev,
                                     workers=workers, tiles_per_chunk=config.tiles_per_chunk)
            else:
                # the pixel kernels read each record as four quads (kernels/rasterize_warp.py: staged in shared memory)
                surf = [_bridge.quad_view(geo, v4), *surf[1:], coop, batch]
                _launch_tiles(_k.render_forward_kernel, n_tiles, ts * ts,
                              [bins.tile_start, bins.tile_end, bins.ids, rays_wp, cam_rec, *surf],
                              [*outs, t_final, sums, last, median_idx, vis_w], device=wdev, workers=workers,
                              tiles_per_chunk=config.tiles_per_chunk)
            if workers > 1:
                visibility = _bridge.empty(n, wp.int32, wdev)
                _bridge.launch_split(_kb.sum_visibility_kernel, n, [vis_w], [visibility], device=wdev)

        # gradient order: uax, vax, nrm, auv, nrm_face, m2, zc, color, opacity
        grad_types = (v3, v3, v3, v3, v3, v2, s, v3, s)

        def backward():
            with section("rasterize_backward"):
                def grad_or_empty(a, t):
                    return a.grad if a.requires_grad else wp.zeros(0, dtype=t, device=wdev)

                targets = [*(a.grad for a in prep), grad_or_empty(opacities, s)]
                if workers == 1:
                    # one worker (CUDA): accumulate straight into the tape's zeroed gradient arrays (same sums
                    # as a zeroed buffer added to them), no buffers to clear and no reduction launch
                    bufs = [g.reshape((1, n)) if g.shape[0] else _bridge.empty((1, n), t, wdev, zero=True)
                            for g, t in zip(targets, grad_types)]
                else:
                    bufs = [_bridge.empty((workers, n), t, wdev, zero=True) for t in grad_types]
                if tiles:
                    scratch = [_bridge.empty((h, w), t, wdev) for t in (s, s, v4)]
                    _launch_worker_tiles(_kt.render_backward_tiles_kernel, n_tiles,
                                         [bins.tile_start, bins.ids, bins.prect, rays_wp, cam_rec, *surf, t_final,
                                          sums, last, median_idx, *(o.grad for o in outs), *scratch],
                                         bufs, device=wdev, workers=workers, tiles_per_chunk=config.tiles_per_chunk)
                else:
                    _launch_tiles(_kbwd.render_backward_kernel, n_tiles, ts * ts,
                                  [bins.tile_start, bins.ids, rays_wp, cam_rec, *surf, t_final, sums, last,
                                   median_idx, *(o.grad for o in outs)],
                                  bufs, device=wdev, workers=workers, tiles_per_chunk=config.tiles_per_chunk)
                if workers > 1:
                    _bridge.launch_split(_kbwd.reduce_gradients_kernel, n, bufs, targets, device=wdev)
                if means2d.requires_grad:
                    # the screen-space gradient from the pixel sums, before the preparation's adjoint adds to m2.grad
                    _bridge.launch_split(_kbwd.shift_gradient_kernel, n,
                                         [cam_rec, uax, vax, nrm, uax.grad, vax.grad, nrm.grad, m2.grad],
                                         [means2d.grad], device=wdev)

        if tape is not None and n > 0:  # N = 0: nothing to differentiate (empty arrays have no grad buffer)
            tape.record_func(backward, [*outs, *prep, *(a for a in (opacities, means2d) if a.requires_grad)])
        return (*outs, visibility)

    return run


def _apply_op(bins, rays, cam_rec, bg: torch.Tensor, means, quats, scales, opacities, colors_or_sh, means2d,
              sh_degree, camera, config: RasterConfig, wdev) -> tuple:
    """The differentiable op on binned surfels: ``(rgb, alpha, depth, median, normal, distortion, visibility)``.
    ``means2d`` only carries the screen-space gradient (its value is never read); ``camera``: its size."""
    if colors_or_sh.ndim == 2:
        sh = colors_or_sh.unsqueeze(1)
        deg = -1
    else:
        sh = colors_or_sh[:, : (sh_degree + 1) ** 2]
        deg = sh_degree
    v3 = _bridge.vec_dtype(means, 3)
    run = _make_run(bins, rays, cam_rec, _bridge.to_warp(bg.reshape(1, 3), v3), deg, camera, config, wdev,
                    means.dtype)
    op = _bridge.WarpOp(
        "rasterize_surfels", run,
        in_dtypes=(v3, _bridge.vec_dtype(means, 4), _bridge.vec_dtype(means, 2), _bridge.float_dtype(means), v3,
                   _bridge.vec_dtype(means, 2)),
        differentiable_inputs=(True,) * 6,
        differentiable_outputs=(True,) * 6 + (False,),
    )
    return _bridge.apply(op, means, quats, scales, opacities, sh, means2d)
