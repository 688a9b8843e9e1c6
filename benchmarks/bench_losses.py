# SPDX-License-Identifier: Apache-2.0
"""Benchmark of the fit's per-iteration loss terms on the CPU (the ``losses`` section of the profile).

Builds the default bunny fit (32 views of 128 px, CPU plan), runs a short warm-up and the TSDF
re-initialisation (so the surfels are the co-evolution's: about 10k lying on the surface), builds the
proxy mesh once, and then times, over every training view, the ``losses`` section of
:class:`wtopo.fitting.objective.Objective` as the fit runs it in the co-evolution (every term on:
photometric, mask, normal, distortion, multi-view, scale, mesh depth, mesh normal). The view's
rendering and the proxy's ray cast are made beforehand and not timed. It also times each term on
its own, forward and forward + backward into the rendered maps (the rasterizer's backward is not
included), and, in the same process, the torch formulations they replace: the photometric term as
torch L1 + :func:`wtopo.metrics.ssim`, the multi-view term's windows scored by the torch op chain the
Warp kernel replaced (``tests/reference/multiview.py``: same pixels, neighbours and masks).

Command (writes nothing; the figures go to benchmarks/losses.md by hand)::

    .venv/bin/python benchmarks/bench_losses.py
    .venv/bin/python benchmarks/bench_losses.py --repeats 5 --warmup 200   # steadier

The ``--section-only`` flag times only the ``losses`` section, with nothing this version added, so
the same script measures an older checkout of the package. ``--quick`` skips the fit: on the bunny's
true depth maps and normals (8 views) it times the multi-view term at the fit's count and at 4,096
pixels, by the Warp kernel and by the torch op chain, and the photometric term fused and in torch,
forward and forward + backward; ``--threads``
sets torch's threads (1 measures the work without the stalls of a shared machine)::

    .venv/bin/python benchmarks/bench_losses.py --quick --threads 1

On a GPU (#60's goal: every per-pixel loss together at most 1 ms an iteration at 800 x 600; a 700 px square
bunny has 490k pixels, 800 x 600 has 480k), every time synchronised so that it includes the kernels, and the
section also with the per-pixel terms eager (:data:`wtopo.fitting.pixel_terms.GRAPHS` off)::

    python benchmarks/bench_losses.py --device cuda --resolution 700 --views 16

``--pixel-terms`` times the section with those terms alone (no scale or mesh terms), as the goal counts them.
"""

from __future__ import annotations

import argparse
import time
import types

import torch
from _from_tests import load  # beside this script

from wtopo import scenes
from wtopo.depth_normals import depth_normals
from wtopo.fitting import FitConfig
from wtopo.fitting.loop import FitRun
from wtopo.fitting.profiling import Timers
from wtopo.fitting.stages import Stage


def build(warmup: int, seed: int, device: str = "cpu", resolution: int | None = None,
          views: int | None = None) -> FitRun:
    """The bunny fit on ``device`` after ``warmup`` warm-up iterations and the TSDF re-initialisation
    (``resolution`` / ``views``: the scene's, default the embedded bunny's 128 px and 32 views)."""
    cfg = FitConfig()
    cfg.runtime.seed = seed
    cfg.runtime.usd_every = 0
    cfg.runtime.progress = False
    cfg.runtime.device = device
    kw = {k: v for k, v in (("resolution", resolution), ("n_views", views)) if v}
    run = FitRun(scenes.load("bunny", **kw), cfg, None, False)
    run._start()
    run._iterate(Stage.WARMUP, 0, warmup)
    run._tsdf_reinit()
    return run


class _FixedProxy:
    """The proxy mesh built once; its ray casts made beforehand (the ``proxy`` and ``raycast`` sections)."""

    def __init__(self, mesh, renders):
        self.mesh, self.renders, self.vi = mesh, renders, 0

    def build(self, surfels):
        return self.mesh

    def render(self, mesh, camera):
        return self.renders[self.vi]


def _leaf(out):
    """The rendered maps as leaves that ask for gradients (the losses' own backward, not the rasterizer's)."""
    fields = ("rgb", "alpha", "median_depth", "normal", "distortion")
    maps = {k: getattr(out, k).detach().clone().requires_grad_() for k in fields}
    return types.SimpleNamespace(overflow=None, **maps)


def _sync() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def _time(fn, repeats: int) -> float:
    """Best-of-``repeats`` seconds of ``fn()`` (one call per view inside ``fn``), the device's work included."""
    best = float("inf")
    for _ in range(repeats):
        _sync()
        t = time.perf_counter()
        fn()
        _sync()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--warmup", type=int, default=100, help="warm-up iterations before the TSDF re-initialisation")
    ap.add_argument("--repeats", type=int, default=3, help="passes over the views; the best is reported")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--section-only", action="store_true", help="only the losses section (runs on older checkouts)")
    ap.add_argument("--quick", action="store_true", help="no fit: the multi-view and photometric terms on true depth")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's, as the fit)")
    ap.add_argument("--device", default="cpu", help="the fit's device (cuda: every time includes the kernels)")
    ap.add_argument("--resolution", type=int, default=None, help="the bunny's image size in px (default 128)")
    ap.add_argument("--views", type=int, default=None, help="the bunny's view count (default 32)")
    ap.add_argument("--kernels", type=int, default=0,
                    help="CUDA: also list this many kernels of the section (forward + backward) by device time")
    ap.add_argument("--pixel-terms", action="store_true",
                    help="the section with the per-pixel terms alone (#60's goal 3: no scale or mesh terms)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.quick:
        _quick(args.repeats)
        return

    t0 = time.perf_counter()
    run = build(args.warmup, args.seed, args.device, args.resolution, args.views)
    s, obj = run.surfels, run.objective
    views = list(range(len(run.train.cameras)))
    with torch.no_grad():
        outs = [_leaf(run.render(s, run.train.cameras[v])) for v in views]
    mesh = run.proxy.build(s)
    with torch.no_grad():
        mrs = [run.proxy.render(mesh, run.train.cameras[v]) for v in views]
    print(f"bunny: {len(views)} training views of {outs[0].rgb.shape[1]}x{outs[0].rgb.shape[0]} px, {len(s)} surfels, "
          f"proxy {'built' if mesh is not None else 'empty'}; set-up {time.perf_counter() - t0:.0f} s; "
          f"torch threads {torch.get_num_threads()}")

    proxy = _FixedProxy(mesh, mrs)
    if args.pixel_terms:  # photometric, mask, normal, distortion and multi-view only
        obj.cfg.losses.scale = 0.0
        obj.mesh_terms = False
    obj.timers = Timers()
    obj.render = lambda surfels, cam, defer_count=False: outs[proxy.vi]
    it = run.warmup_end  # the co-evolution: every term on

    def section(backward: bool):
        for v in views:
            proxy.vi = v
            t = obj(Stage.COEVOLUTION, it, v, s, proxy)
            if backward:
                sum(t.losses.values()).backward()

    names = sorted(obj(Stage.COEVOLUTION, it, 0, s, proxy).losses)
    n = len(views)
    rows = {}
    rows["losses section (forward)"] = _time(lambda: section(False), args.repeats) / n
    rows["losses forward + backward"] = _time(lambda: section(True), args.repeats) / n
    if s.means.is_cuda:  # the same with the per-pixel terms eager (wtopo.fitting.pixel_terms.GRAPHS off)
        from wtopo.fitting import pixel_terms
        pixel_terms.GRAPHS = False
        rows["losses forward + backward, terms eager"] = _time(lambda: section(True), args.repeats) / n
        pixel_terms.GRAPHS = True
        failed = obj.pixel_terms.failures
        print(f"graphed sets: {len(obj.pixel_terms._graphs) - len(failed)}, failed: {failed}")  # noqa: SLF001
    print(f"terms: {', '.join(names)}")
    for k, v in rows.items():
        print(f"  {k:40s} {1000 * v:8.2f} ms/it")
    if args.kernels and s.means.is_cuda:
        from gpu_timing import profile_kernels  # beside this script

        profile_kernels(lambda: section(True), f"the losses section, forward + backward, {n} views", calls=1,
                        top=args.kernels, per=n)
    if args.section_only:
        return
    _terms(run, outs, mrs, args.repeats)


def _terms(run, outs, mrs, repeats: int) -> None:
    """Each term alone (forward and forward + backward), and the formulations they replace."""
    from wtopo.fitting import losses as L
    from wtopo.fitting import objective as O
    from wtopo.metrics import ssim

    cfg, train, s = run.cfg, run.train, run.surfels
    views = range(len(outs))
    n = len(outs)
    it = run.warmup_end
    mv = run.objective.multiview
    h, w = outs[0].alpha.shape
    mv_count = mv.count(h, w) if hasattr(mv, "count") else mv.pixels
    torch_loss = load("reference/multiview.py").multiview_loss_torch

    def photo_torch(o, v):
        img = train.images[v]
        return (1 - O._DSSIM) * L.l1(o.rgb, img) + O._DSSIM * (1 - ssim(o.rgb, img))

    def normal(o, v):
        cam = train.cameras[v]
        covered = o.alpha.detach() >= O.ALPHA_COVERED
        ro, rd = cam.pixel_rays(o.alpha.device)
        dn, dm = depth_normals(o.median_depth, ro, rd, covered)
        return L.normal_consistency(o.normal, dn, o.alpha, dm)

    def mesh_terms(o, v):
        mr = mrs[v]
        both = mr.mask & (o.alpha.detach() >= O.ALPHA_COVERED)
        return (L.mesh_depth_loss(o.median_depth, mr.depth, both, eps=O._DEPTH_EPS, form="log_ratio",
                                  extent=O.ROI_EXTENT, debias=cfg.losses.mesh_depth_debias)
                + L.mesh_normal_loss(o.normal, mr.normal, both))

    terms = {
        "photo": lambda o, v: L.photometric(o.rgb, train.images[v], O._DSSIM),
        "photo (torch L1 + SSIM)": photo_torch,
        "mask": lambda o, v: L.mask_loss(o.alpha, train.masks[v].to(o.alpha.dtype)),
        "normal": normal,
        "distortion": lambda o, v: L.distortion(o.distortion),
        "scale": lambda o, v: L.scale_regularizer(s.scales, O._MAX_ANISOTROPY),
        "mesh depth + normal": mesh_terms,
    }
    if all(mv.has_neighbours(v) for v in views):  # a capture too sparse for neighbours has no multi-view term
        terms[f"multiview ({mv_count} px)"] = lambda o, v: mv(it, v, o.median_depth, o.normal, o.alpha)
        terms[f"multiview ({mv_count} px, torch ops)"] = lambda o, v: torch_loss(mv, it, v, o.median_depth, o.normal,
                                                                                o.alpha)
    fwd, both = {}, {}
    for name, f in terms.items():
        def go(backward, f=f):
            for v in views:
                r = f(outs[v], v)
                if backward and r.requires_grad:
                    r.backward()
        go(True)  # first call: caches, compiles
        fwd[name] = _time(lambda: go(False), repeats) / n
        both[name] = _time(lambda: go(True), repeats) / n
    print(f"  {'term':40s} {'forward':>8s} {'fwd+bwd':>8s}  ms/it")
    for name in terms:
        print(f"  {name:40s} {1000 * fwd[name]:8.2f} {1000 * both[name]:8.2f}")
    mv_name = f"multiview ({mv_count} px)"
    pairs = (("photo", "photo (torch L1 + SSIM)"), (mv_name, f"{mv_name[:-1]}, torch ops)"))
    for new, old in pairs:
        if new not in fwd:
            continue
        print(f"  {new} vs {old}: {fwd[old] / fwd[new]:.2f}x faster forward, {both[old] / both[new]:.2f}x fwd+bwd")


def _quick(repeats: int, views: int = 8) -> None:
    """The multi-view and photometric terms on the bunny's true depth, normals and (noisy) colours."""
    import numpy as np

    from wtopo.fitting import losses as L
    from wtopo.fitting.multiview import MultiViewNCC
    from wtopo.fitting.objective import _DSSIM, _MULTIVIEW_FRACTION, _MULTIVIEW_PIXELS
    from wtopo.metrics import ssim

    torch_loss = load("reference/multiview.py").multiview_loss_torch
    sc = scenes.load("bunny").normalized()
    cams, imgs = sc.cameras, sc.images
    g = torch.Generator().manual_seed(0)
    maps = []
    for v in range(views):
        d = sc.depths[v].float().clone()
        o, r = cams[v].pixel_rays("cpu")
        n, _ = depth_normals(d, o, r, d > 0)
        rgb = (imgs[v] + 0.05 * torch.randn(imgs[v].shape, generator=g)).clamp(0, 1)
        maps.append((d, n, (d > 0).float(), rgb))
    center = np.full(3, 0.5)
    fit_mv = MultiViewNCC(cams, imgs, center, pixels=_MULTIVIEW_PIXELS, fraction=_MULTIVIEW_FRACTION)
    old_mv = MultiViewNCC(cams, imgs, center, pixels=4096)
    h, w = imgs[0].shape[:2]

    def multiview(m):
        return lambda v, d, n, a, rgb: m(1000, v, d.requires_grad_(), n.requires_grad_(), a)

    def multiview_torch(m):
        return lambda v, d, n, a, rgb: torch_loss(m, 1000, v, d.requires_grad_(), n.requires_grad_(), a)

    def photo_torch(v, d, n, a, rgb):
        p = rgb.requires_grad_()
        return (1 - _DSSIM) * L.l1(p, imgs[v]) + _DSSIM * (1 - ssim(p, imgs[v]))

    c = fit_mv.count(h, w)
    terms = {f"multiview ({c} px, Warp)": multiview(fit_mv), f"multiview ({c} px, torch ops)": multiview_torch(fit_mv),
             "multiview (4096 px, Warp)": multiview(old_mv), "multiview (4096 px, torch ops)": multiview_torch(old_mv),
             "photo (fused Warp)": lambda v, d, n, a, rgb: L.photometric(rgb.requires_grad_(), imgs[v], _DSSIM),
             "photo (torch L1 + SSIM)": photo_torch}

    def go(f, backward):
        for v, m in enumerate(maps):
            r = f(v, *m)
            if backward:
                r.backward()

    for f in terms.values():
        go(f, True)  # caches, kernel loads
    print(f"bunny true depth: {views} views of {w}x{h} px; torch threads {torch.get_num_threads()}")
    print(f"  {'term':32s} {'forward':>8s} {'fwd+bwd':>8s}  ms/it (best of {repeats})")
    for name, f in terms.items():
        fwd = _time(lambda f=f: go(f, False), repeats) / views
        both = _time(lambda f=f: go(f, True), repeats) / views
        print(f"  {name:32s} {1000 * fwd:8.2f} {1000 * both:8.2f}")


if __name__ == "__main__":
    main()
