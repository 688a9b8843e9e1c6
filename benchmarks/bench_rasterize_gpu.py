# SPDX-License-Identifier: Apache-2.0
"""GPU benchmark: the surfel rasterizer against gsplat's ``rasterization_2dgs``, the fused photometric loss,
and a fit-like training step, timed with CUDA events in one process.

What is timed (median of ``--repeats`` after ``--warmup`` calls; the first calls also compile the Warp
kernels, minutes on a machine without a kernel cache):

1. Rasterizer, ``--res`` x ``--res`` pixels, one camera, ``--sizes`` random surfels (SH degree 3), float32:
   wtopo's public :func:`wtopo.ops.rasterize_surfels` as a user's loop calls it (argument checks in one host
   read; after two calls of the same shape a CUDA graph's replay and one read of its pair count), the same
   with replays off (``wtopo_public_eager``, ``RasterConfig(replay=False)``: the checks, the default near
   plane's median and the exact pair count, host synchronisations each), wtopo's fit path
   ``wtopo.rasterize._rasterize_trusted`` with ``defer_count`` (no host synchronisation; also with Warp's own
   overload lookup at every launch, ``warp_lookup``), and,
   when ``import gsplat`` works, gsplat's ``rasterization_2dgs`` on the same surfels and camera
   (``render_mode="RGB+ED"``, ``distloss=True``: colour, alpha, expected and median depth, normals and
   distortion, as wtopo renders). Forward alone and forward +
   backward of ``sum(image * random weights)`` over all six images. Two modes: ``latency`` (the
   device is idle at each call's start and the time runs until its last kernel ends: host overhead
   and synchronisations count in full) and ``pipelined`` (``--repeats`` calls back to back, events
   around the batch, divided by the count: what a training loop that does not wait sees).
2. Fused photometric loss ``0.8 L1 + 0.2 (1 - SSIM)`` at ``--loss-size`` (W H), forward and forward +
   backward, against the torch formulation (``wtopo.metrics.ssim``: grouped separable convolutions).
3. A fit-like step at ``--step-size`` pixels with ``--step-surfels`` surfels: render, photometric +
   distortion loss, backward, Adam, one host read of the loss and the overflow flag; per-stage CUDA
   event times and the wall time per iteration, public path and fit path.

Run from the repository root (needs torch with CUDA, warp-lang, numpy; gsplat optional):

    .venv/bin/python benchmarks/bench_rasterize_gpu.py --device cuda:0 --out /tmp/bench_gpu

Prints tables and writes ``<out>/bench_rasterize_gpu.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import traceback

import torch
import warp as wp
from bench_rasterize import scene as cpu_scene  # noqa: E402
from gpu_timing import cuda_event, profile_kernels, time_latency, time_pipelined  # noqa: E402

import wtopo  # noqa: E402
from wtopo import _bridge  # noqa: E402
from wtopo import rasterize as R  # noqa: E402
from wtopo.photometric import photometric_loss  # noqa: E402
from wtopo.rasterize import _run as K  # noqa: E402  kernel-mode switches

IMAGES = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")


# -- scene ---------------------------------------------------------------------------------------------


def make_camera(width: int, height: int):
    """Pinhole camera 3 units in front of the origin, horizontal field of view 0.7 rad."""
    return wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.7, width=width, height=height)


def make_surfels(n: int, device, seed: int = 0):
    """``n`` random surfels in a 2 x 2 x 2 box, leaf tensors (means, quats, scales, opacities, sh [N, 16, 3]).

    The scene of ``benchmarks/bench_rasterize.py`` (scales shrink as 1 / sqrt(n): about the same total
    screen area at every size; standard deviations of ~7 px at 100k and ~2 px at 1M on an 800 px image).
    """
    return cpu_scene(n, 8, device, seed)[1]


# -- the renderers, each returning the six images ------------------------------------------------------


def wtopo_public(params, cam):
    out = R.rasterize_surfels(*params, cam)
    return {k: getattr(out, k) for k in IMAGES}


def wtopo_public_eager(params, cam):
    out = R.rasterize_surfels(*params, cam, config=R.RasterConfig(replay=False))
    return {k: getattr(out, k) for k in IMAGES}


def make_wtopo_fit_path(cam):
    bg = None
    cfg = R.RasterConfig()
    last = {}

    def render(params):
        nonlocal bg
        if bg is None:
            bg = torch.zeros(3, dtype=params[0].dtype, device=params[0].device)
        out = R._rasterize_trusted(*params, cam, sh_degree=None, background=bg, config=cfg, defer_count=True)
        last["overflow"] = out.overflow
        return {k: getattr(out, k) for k in IMAGES}

    return render, last


def kernel_mode(render, coop: bool, batch: int):
    """``render`` with other pixel-kernel settings: ``coop=False`` is the previous CUDA kernels' work order
    (one atomic per pixel), ``batch=1`` warp cooperation without the batched id loads and prefetches."""

    def run(*a):
        saved = K.COOPERATIVE_WARPS, K.PREFETCH_BATCH
        K.COOPERATIVE_WARPS, K.PREFETCH_BATCH = coop, batch
        try:
            return render(*a)
        finally:
            K.COOPERATIVE_WARPS, K.PREFETCH_BATCH = saved

    return run


def warp_lookup(render):
    """``render`` with Warp's own overload lookup at every launch of a generic kernel (``_bridge.RESOLVE_OVERLOADS``
    off): the host time the resolved launches save."""

    def run(*a):
        saved = _bridge.RESOLVE_OVERLOADS
        _bridge.RESOLVE_OVERLOADS = False
        try:
            return render(*a)
        finally:
            _bridge.RESOLVE_OVERLOADS = saved

    return run


def gsplat_inputs(params, cam, near: float):
    """Leaves of gsplat for the same surfels: scales [N, 3] (the third is unused by 2DGS), viewmats, Ks."""
    means, quats, scales, ops, sh = (p.detach() for p in params)
    dev = means.device
    third = scales.min(dim=-1, keepdim=True).values
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, torch.cat([scales, third], -1), ops, sh)]
    viewmat = torch.as_tensor(cam.world_to_camera, dtype=torch.float32, device=dev)[None]
    K = torch.as_tensor(cam.K, dtype=torch.float32, device=dev)[None]
    return leaves, viewmat, K


def make_gsplat(cam, near: float, far: float):
    from gsplat import rasterization_2dgs

    extra = {"distloss": True}  # dropped if this gsplat version does not take it

    def render(leaves, viewmat, K):
        means, quats, scales, ops, sh = leaves
        try:
            res = rasterization_2dgs(means, quats, scales, ops, sh, viewmat, K, cam.width, cam.height,
                                     near_plane=near, far_plane=far, sh_degree=3, render_mode="RGB+ED", packed=False,
                                     **extra)
        except TypeError as exc:
            if not extra or "distloss" not in str(exc):
                raise
            print(f"gsplat: {exc}; calling without distloss")
            extra.clear()
            return render(leaves, viewmat, K)
        colors, alphas, normals, _surf_normals, distort, median = res[:6]
        return {"rgb": colors[0, ..., :3], "alpha": alphas[0, ..., 0], "depth": colors[0, ..., 3],
                "median_depth": median[0, ..., 0], "normal": normals[0], "distortion": distort[0, ..., 0]}

    return render


# -- timing: gpu_timing.py -------------------------------------------------------------------------------


def _weights(h: int, w: int, device, seed: int = 1) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {k: torch.randn((h, w, 3) if k in ("rgb", "normal") else (h, w), generator=g).to(device) for k in IMAGES}


def _fwd_bwd(render, args, leaves, ups):
    def fwd():
        with torch.no_grad():
            render(*args)

    def both():
        for p in leaves:
            p.grad = None
        imgs = render(*args)
        sum((imgs[k] * u).sum() for k, u in ups.items()).backward()

    return fwd, both


# -- sections ----------------------------------------------------------------------------------------------


def bench_rasterizer(args, device) -> list[dict]:
    rows = []
    try:
        import gsplat

        gsplat_version = getattr(gsplat, "__version__", "?")
    except Exception as exc:  # noqa: BLE001 - any import failure means: no peer
        gsplat_version = None
        print(f"gsplat not importable ({type(exc).__name__}: {exc}); timing wtopo only")
    if args.no_gsplat:
        gsplat_version = None
    cam = make_camera(args.res, args.res)
    ups = _weights(args.res, args.res, device)
    for n in args.sizes:
        params = make_surfels(n, device)
        ref = R.rasterize_surfels(*params, cam)
        near, far = ref.near, ref.far
        row = {"surfels": n, "res": args.res, "near": near, "far": far,
               "coverage_wtopo": float((ref.alpha > 0).float().mean())}
        fit_render, last = make_wtopo_fit_path(cam)
        impls = {"wtopo_public": (lambda p: wtopo_public(p, cam), (params,), params),
                 "wtopo_public_eager": (lambda p: wtopo_public_eager(p, cam), (params,), params),
                 "wtopo_fit_path": (fit_render, (params,), params),
                 "wtopo_fit_per_pixel": (kernel_mode(fit_render, False, 1), (params,), params),
                 "wtopo_fit_no_batch": (kernel_mode(fit_render, True, 1), (params,), params),
                 "wtopo_fit_warp_lookup": (warp_lookup(fit_render), (params,), params)}
        impls = {k: v for k, v in impls.items() if not args.impls or k in args.impls}
        if gsplat_version is not None:
            try:
                leaves, viewmat, K = gsplat_inputs(params, cam, near)
                g_render = make_gsplat(cam, near, far)
                with torch.no_grad():
                    gi = g_render(leaves, viewmat, K)
                    row["coverage_gsplat"] = float((gi["alpha"] > 0).float().mean())
                    row["alpha_mean_abs_diff"] = float((gi["alpha"] - ref.alpha).abs().mean())
                    row["rgb_mean_abs_diff"] = float((gi["rgb"] - ref.rgb).abs().mean())
                impls["gsplat_2dgs"] = (g_render, (leaves, viewmat, K), leaves)
            except Exception as exc:  # noqa: BLE001 - report and keep timing wtopo
                row["gsplat_error"] = f"{type(exc).__name__}: {exc}"
                print(f"gsplat failed at N={n}: {row['gsplat_error']}")
                traceback.print_exc()
        for name, (render, rargs, leaves) in impls.items():
            fwd, both = _fwd_bwd(render, rargs, leaves, ups)
            torch.cuda.reset_peak_memory_stats(device)
            row[name] = {"forward": time_latency(fwd, args.warmup, args.repeats),
                         "forward_backward": time_latency(both, args.warmup, args.repeats),
                         "forward_pipelined": time_pipelined(fwd, args.warmup, args.repeats),
                         "forward_backward_pipelined": time_pipelined(both, args.warmup, args.repeats),
                         "torch_peak_mb": torch.cuda.max_memory_allocated(device) / 2**20}
        if args.profile:
            for name in ("wtopo_fit_per_pixel", "wtopo_fit_no_batch", "wtopo_fit_path", "gsplat_2dgs"):
                if name in impls:
                    render, rargs, leaves = impls[name]
                    row.setdefault("profile", {})[name] = profile_kernels(_fwd_bwd(render, rargs, leaves, ups)[1],
                                                                          f"{name}, N={n}, forward + backward")
        if last.get("overflow") is not None:
            row["fit_path_overflow_last_call"] = bool(last["overflow"])
        rows.append(row)
        del params, ref
        torch.cuda.empty_cache()
    return rows


def print_rasterizer(rows) -> None:
    print("\nRasterizer, one camera (ms; latency = from an idle device, pipelined = back-to-back calls)")
    print(f"{'N':>9} {'impl':<20} {'fwd':>8} {'fwd+bwd':>8} {'fwd pipe':>9} {'f+b pipe':>9} {'host fwd':>9} "
          f"{'peak MB':>8}")
    for r in rows:
        for name in ("wtopo_public", "wtopo_public_eager", "wtopo_fit_path", "wtopo_fit_per_pixel",
                     "wtopo_fit_no_batch", "wtopo_fit_warp_lookup", "gsplat_2dgs"):
            if name not in r:
                continue
            t = r[name]
            print(f"{r['surfels']:>9} {name:<20} {t['forward']['ms']:8.2f} {t['forward_backward']['ms']:8.2f} "
                  f"{t['forward_pipelined']['ms']:9.2f} {t['forward_backward_pipelined']['ms']:9.2f} "
                  f"{t['forward']['host_ms']:9.2f} {t['torch_peak_mb']:8.0f}")
        if "gsplat_2dgs" in r:
            g = r["gsplat_2dgs"]
            for name in ("wtopo_public", "wtopo_public_eager", "wtopo_fit_path", "wtopo_fit_per_pixel",
                         "wtopo_fit_no_batch", "wtopo_fit_warp_lookup"):
                if name not in r:
                    continue
                t = r[name]
                ratios = [t[k]["ms"] / g[k]["ms"] for k in ("forward", "forward_backward", "forward_pipelined",
                                                            "forward_backward_pipelined")]
                r.setdefault("ratios_vs_gsplat", {})[name] = ratios
                label = name.removeprefix("wtopo_") + "/gsplat"
                print(f"{'':>9} {label:<20} " + " ".join(f"{x:8.2f}x" for x in ratios))
            print(f"{'':>9} coverage wtopo {r['coverage_wtopo']:.3f} "
                  f"gsplat {r.get('coverage_gsplat', float('nan')):.3f}, "
                  f"mean |alpha diff| {r.get('alpha_mean_abs_diff', float('nan')):.4f}, "
                  f"mean |rgb diff| {r.get('rgb_mean_abs_diff', float('nan')):.4f}")


def _torch_photometric():
    try:
        from wtopo.metrics import ssim
    except Exception as exc:  # noqa: BLE001 - scipy missing: no torch baseline
        print(f"wtopo.metrics not importable ({type(exc).__name__}: {exc}); no torch baseline for the loss")
        return None

    def loss(pred, target):
        return 0.8 * (pred - target).abs().mean() + 0.2 * (1.0 - ssim(pred, target))

    return loss


def bench_loss(args, device) -> dict:
    w, h = args.loss_size
    g = torch.Generator().manual_seed(2)
    target = torch.rand(h, w, 3, generator=g).to(device)
    pred = (target + 0.1 * torch.randn(h, w, 3, generator=g).to(device)).clamp(0, 1).requires_grad_(True)
    impls = {"fused_warp": lambda: photometric_loss(pred, target, dssim=0.2)}
    tl = _torch_photometric()
    if tl is not None:
        impls["torch_ssim"] = lambda: tl(pred, target)
    res = {"size": [w, h]}
    for name, f in impls.items():
        def fwd(f=f):
            with torch.no_grad():
                f()

        def both(f=f):
            pred.grad = None
            f().backward()

        res[name] = {"forward": time_latency(fwd, args.warmup, args.repeats),
                     "forward_backward": time_latency(both, args.warmup, args.repeats),
                     "forward_pipelined": time_pipelined(fwd, args.warmup, args.repeats),
                     "forward_backward_pipelined": time_pipelined(both, args.warmup, args.repeats)}
    if tl is not None:
        a, b = photometric_loss(pred, target).item(), tl(pred, target).item()
        res["value_fused"], res["value_torch"] = a, b
    return res


def print_loss(res) -> None:
    w, h = res["size"]
    print(f"\nPhotometric loss 0.8 L1 + 0.2 (1 - SSIM), {w}x{h}x3 (ms)")
    print(f"{'impl':<12} {'fwd':>8} {'fwd+bwd':>8} {'fwd pipe':>9} {'f+b pipe':>9}")
    for name in ("fused_warp", "torch_ssim"):
        if name in res:
            t = res[name]
            print(f"{name:<12} {t['forward']['ms']:8.3f} {t['forward_backward']['ms']:8.3f} "
                  f"{t['forward_pipelined']['ms']:9.3f} {t['forward_backward_pipelined']['ms']:9.3f}")
    if "value_torch" in res:
        print(f"values: fused {res['value_fused']:.7f}, torch {res['value_torch']:.7f}")


def _step_path(path: str, args, device, cam) -> dict:
    """Fit-like iterations through one rasterizer path: mean CUDA-event ms per stage, median wall ms."""
    w, h = cam.width, cam.height
    means, quats, scales, ops, sh = (p.detach() for p in make_surfels(args.step_surfels, device, seed=3))
    params = {"means": means.clone(), "quats": quats.clone(), "log_scales": scales.log(),
              "opacity_logits": torch.logit(ops), "sh": sh.clone()}
    for p in params.values():
        p.requires_grad_(True)
    opt = torch.optim.Adam(list(params.values()), lr=1e-3)
    g = torch.Generator().manual_seed(4)
    target = torch.rand(h, w, 3, generator=g).to(device)
    bg = torch.zeros(3, device=device)
    cfg = R.RasterConfig(filter_sigma=0.35)  # the fit's filter
    stages = ("render", "losses", "backward", "optimizer", "read")
    sums = dict.fromkeys(stages, 0.0)
    overflows = 0
    wall = []
    vals = [float("nan"), 0.0]
    for it in range(args.warmup + args.step_iters):
        ev = [cuda_event() for _ in range(len(stages) + 1)]
        t0 = time.perf_counter()
        ev[0].record()
        a = (params["means"], params["quats"], params["log_scales"].exp(), torch.sigmoid(params["opacity_logits"]),
             params["sh"])
        K.COOPERATIVE_WARPS = path != "fit_path_per_pixel"
        if path == "public":
            o = R.rasterize_surfels(*a, cam, background=bg, config=cfg)
        else:
            o = R._rasterize_trusted(*a, cam, sh_degree=None, background=bg, config=cfg, defer_count=True)
        ev[1].record()
        loss = photometric_loss(o.rgb, target, dssim=0.2) + 0.01 * o.distortion.mean()
        ev[2].record()
        loss.backward()
        K.COOPERATIVE_WARPS = True
        ev[3].record()
        opt.step()
        opt.zero_grad(set_to_none=True)
        ev[4].record()
        flag = o.overflow.double().view(1) if o.overflow is not None else loss.new_zeros(1, dtype=torch.float64)
        vals = torch.cat([loss.detach().double().view(1), flag]).tolist()  # the one host read per step
        ev[5].record()
        wall.append(1e3 * (time.perf_counter() - t0))
        overflows += int(vals[1] > 0)
        if it >= args.warmup:
            torch.cuda.synchronize()
            for k, st in enumerate(stages):
                sums[st] += ev[k].elapsed_time(ev[k + 1])
    n = max(1, args.step_iters)
    return {"ms_per_iteration": {st: v / n for st, v in sums.items()},
            "wall_ms_per_iteration": statistics.median(wall[args.warmup:]), "overflows": overflows,
            "final_loss": vals[0], "torch_peak_mb": torch.cuda.max_memory_allocated(device) / 2**20,
            "warp_pool_high_mb": _warp_pool_high_mb(device)}


def _warp_pool_high_mb(device) -> float | None:
    """High-water mark of Warp's CUDA memory pool since the process started [MB] (None where unavailable)."""
    try:
        return wp.get_mempool_used_mem_high(wp.device_from_torch(device)) / 2**20
    except Exception:  # noqa: BLE001 - older Warp or no pool: not reported
        return None


def bench_step(args, device) -> dict:
    """Fit-like iterations (render, losses, backward, Adam, one read), public path and fit path."""
    w, h = args.step_size
    cam = make_camera(w, h)
    out = {"size": [w, h], "surfels": args.step_surfels, "iterations": args.step_iters}
    for path in ("public", "fit_path", "fit_path_per_pixel"):
        torch.cuda.reset_peak_memory_stats(device)
        out[path] = _step_path(path, args, device, cam)
    return out


def print_step(res) -> None:
    w, h = res["size"]
    print(f"\nFit-like step, {res['surfels']} surfels, {w}x{h}, {res['iterations']} iterations (ms per iteration; "
          f"stage = CUDA events between its launches, wall = host time of the whole step)")
    stages = list(res["public"]["ms_per_iteration"])
    print(f"{'path':<18} " + " ".join(f"{s:>9}" for s in stages) + f" {'sum':>8} {'wall':>8}")
    for path in ("public", "fit_path", "fit_path_per_pixel"):
        t = res[path]["ms_per_iteration"]
        print(f"{path:<18} " + " ".join(f"{t[s]:9.3f}" for s in stages) + f" {sum(t.values()):8.3f} "
              f"{res[path]['wall_ms_per_iteration']:8.3f}")
    for path in ("public", "fit_path", "fit_path_per_pixel"):
        r = res[path]
        pool = r["warp_pool_high_mb"]
        print(f"{path}: torch peak {r['torch_peak_mb']:.0f} MB, Warp pool high-water "
              f"{'n/a' if pool is None else f'{pool:.0f} MB'} (since process start), overflows {r['overflows']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--res", type=int, default=800)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--loss-size", type=int, nargs=2, default=[800, 600], metavar=("W", "H"))
    ap.add_argument("--step-size", type=int, nargs=2, default=[800, 600], metavar=("W", "H"))
    ap.add_argument("--step-surfels", type=int, default=150_000)
    ap.add_argument("--step-iters", type=int, default=50)
    ap.add_argument("--no-gsplat", action="store_true", help="do not time gsplat even when importable")
    ap.add_argument("--impls", nargs="+", metavar="NAME",
                    help="time only these of wtopo's rasterizer paths (wtopo_public, wtopo_fit_path, ...); "
                         "gsplat_2dgs follows --no-gsplat")
    ap.add_argument("--profile", action="store_true",
                    help="rasterizer section: also print the CUDA kernel times of the fit path (both kernel modes) "
                         "and gsplat (torch.profiler)")
    ap.add_argument("--only", nargs="+", choices=["rasterizer", "loss", "step"], default=["rasterizer", "loss", "step"])
    ap.add_argument("--out", default="/tmp/bench_rasterize_gpu", help="folder for bench_rasterize_gpu.json")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("CUDA is not available: this benchmark needs a GPU (benchmarks/bench_rasterize.py times the CPU)")
        return 2
    device = torch.device(args.device)
    torch.cuda.set_device(device)
    os.makedirs(args.out, exist_ok=True)
    info = {"device": torch.cuda.get_device_name(device), "torch": torch.__version__, "warp": wp.config.version,
            "python": platform.python_version(), "argv": sys.argv}
    print(f"{info['device']}, torch {info['torch']}, warp {info['warp']}")
    result = {"info": info}
    sections = {"rasterizer": (bench_rasterizer, print_rasterizer), "loss": (bench_loss, print_loss),
                "step": (bench_step, print_step)}
    failed = False
    for name in args.only:
        bench, show = sections[name]
        try:
            result[name] = bench(args, device)
            show(result[name])
        except Exception as exc:  # noqa: BLE001 - keep the other sections and say what failed
            failed = True
            result[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
            print(f"\nsection {name} failed:\n{result[name]['traceback']}")
        with open(os.path.join(args.out, "bench_rasterize_gpu.json"), "w") as f:
            json.dump(result, f, indent=1, default=str)
    print(f"\nwrote {os.path.join(args.out, 'bench_rasterize_gpu.json')}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
