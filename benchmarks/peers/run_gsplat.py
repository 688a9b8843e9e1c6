# SPDX-License-Identifier: Apache-2.0
"""gsplat's ``rasterization_2dgs`` with the 2DGS recipe on an exchange folder (the peers benchmark).

The recipe of gsplat's ``examples/simple_trainer_2dgs.py`` with its 2DGS losses on: 30,000 steps,
L1 + 0.2 D-SSIM, normal consistency (0.05 from step 7,000), depth distortion (0.01 from step 3,000),
SH degree 3 (one more every 1,000 steps), initial points from the exchange folder, gsplat's
``DefaultStrategy`` on the 2DGS gradient with the trainer's settings (``prune_opa`` 0.05; thresholds in
the trainer's normalised world, where the median camera distance is 1) and its opacity reset every
3,000 steps (gsplat 1.5.3's own reset never fires: ``step % reset_every == 0 & step > 0`` is always
false; fixed upstream after 1.5.3 in #776, so it is done here); then 2DGS's TSDF mesh (median depth,
voxel 0.004, truncation 0.016, depth cut 3.0, largest cluster). On a masked capture the masks are the
images' alpha: each step composites the photograph on a random background outside its mask, as gsplat's
trainer does for RGBA images with ``random_bkgd`` (``--no-mask-bg``: train on the photographs as they are;
on a black background the splats outside the visual hull then turn black and hide the object from
held-out views, see ``benchmarks/peers.md``).

    python benchmarks/peers/run_gsplat.py EXCH OUT [--iterations 30000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _result import Clock, write_result  # noqa: E402
from _tsdf import tsdf_mesh  # noqa: E402
from exchange import load  # noqa: E402

C0 = 0.28209479177387814


def _ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """SSIM of [1, 3, H, W] images, 11-px Gaussian window (sigma 1.5), zero-padded as in 3DGS's loss."""
    g = torch.exp(-((torch.arange(11, device=x.device) - 5.0) ** 2) / (2 * 1.5 ** 2))
    g = (g / g.sum())
    w = (g[:, None] * g[None, :]).expand(3, 1, 11, 11).contiguous()

    def blur(t):
        return F.conv2d(t, w, padding=5, groups=3)
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))).mean()


def _knn_scale(points: torch.Tensor) -> torch.Tensor:
    """Mean distance to the 3 nearest neighbours, per point (chunked)."""
    out = []
    for chunk in points.split(4096):
        d = torch.cdist(chunk, points)
        out.append(d.topk(4, largest=False).values[:, 1:].pow(2).mean(-1).sqrt())
    return torch.cat(out).clamp_min(1e-7)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("exchange")
    ap.add_argument("out")
    ap.add_argument("--iterations", type=int, default=30_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reset-opacity", type=float, default=None,
                    help="opacity the periodic reset clamps to (default: gsplat's 2 * prune_opa = 0.1; 2DGS uses 0.01)")
    ap.add_argument("--no-mask-bg", dest="mask_bg", action="store_false",
                    help="masked captures: train on the photographs as they are, not on a random background "
                         "outside the masks")
    ap.add_argument("--save-at", type=int, nargs="*", default=[7000, 15000],
                    help="also save the splats at these steps (splats_STEP.pt), for --mesh-only")
    ap.add_argument("--mesh-only", type=int, default=None, metavar="STEP",
                    help="skip training: mesh and render the splats an earlier run saved at STEP")
    a = ap.parse_args(argv)

    from gsplat import rasterization_2dgs
    from gsplat.strategy import DefaultStrategy
    from gsplat.strategy.ops import reset_opa

    dev = torch.device("cuda")
    torch.manual_seed(a.seed)
    ex = load(a.exchange)
    clock = Clock()
    images = torch.stack([torch.from_numpy(ex.image(i)) for i in ex.train]).to(dev)
    Ks = torch.tensor(ex.K[ex.train], dtype=torch.float32, device=dev)
    # gsplat's pixel centres are at +0.5 like ours: the K carries over unchanged
    viewmats = torch.tensor(ex.w2c[ex.train], dtype=torch.float32, device=dev)
    c2w = torch.linalg.inv(viewmats)
    centres = c2w[:, :3, 3]
    scene_scale = float((centres - centres.mean(0)).norm(dim=-1).max()) * 1.1
    # simple_trainer_2dgs calls initialize_state() with its default scene_scale 1.0 in a world that its
    # COLMAP parser scaled to a median camera distance of 1 (to the cameras' focus): that unit, here (the focus by
    # least squares: a forward-facing rig's parallel axes leave it undetermined along them, pinv takes the nearest)
    axes = c2w[:, :3, 2]
    proj = torch.eye(3, device=dev) - axes[:, :, None] * axes[:, None, :]
    focus = (torch.linalg.pinv(proj.sum(0)) @ (proj @ centres[:, :, None]).sum(0))[:, 0]
    unit = float((centres - focus).norm(dim=-1).median())
    bg = torch.tensor(ex.meta["background"] or [0.0, 0.0, 0.0], dtype=torch.float32, device=dev)
    W, H = ex.width, ex.height
    masks = None
    if a.mask_bg and ex.masked:
        masks = torch.stack([torch.from_numpy(ex.mask(i)) for i in ex.train]).to(dev)[..., None].float()

    pts, col = ex.points()
    pts = torch.tensor(pts, dtype=torch.float32, device=dev)
    col = torch.tensor(col, dtype=torch.float32, device=dev)
    n = len(pts)
    sh = torch.zeros(n, 16, 3, device=dev)
    sh[:, 0] = (col - 0.5) / C0
    params = {
        "means": (pts, 1.6e-4 * scene_scale),
        "scales": (torch.log(_knn_scale(pts))[:, None].repeat(1, 3), 5e-3),
        "quats": (torch.rand(n, 4, device=dev), 1e-3),
        "opacities": (torch.logit(torch.full((n,), 0.1, device=dev)), 5e-2),
        "sh0": (sh[:, :1].contiguous(), 2.5e-3),
        "shN": (sh[:, 1:].contiguous(), 2.5e-3 / 20),
    }
    splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, (v, _) in params.items()})
    opts = {k: torch.optim.Adam([{"params": splats[k], "lr": lr, "name": k}], eps=1e-15)
            for k, (_, lr) in params.items()}
    sched = torch.optim.lr_scheduler.ExponentialLR(opts["means"], gamma=0.01 ** (1.0 / a.iterations))
    # simple_trainer_2dgs's Config: prune_opa 0.05 (DefaultStrategy's own default is 0.005); the rest as the defaults
    strategy = DefaultStrategy(key_for_gradient="gradient_2dgs", verbose=False, prune_opa=0.05, grow_grad2d=0.0002,
                               grow_scale3d=0.01, prune_scale3d=0.1, refine_start_iter=500, refine_stop_iter=15_000,
                               reset_every=3000, refine_every=100, absgrad=False)
    strategy.check_sanity(splats, opts)
    state = strategy.initialize_state(scene_scale=unit)
    reset_value = 2.0 * strategy.prune_opa if a.reset_opacity is None else a.reset_opacity

    def render(sel_view, K, sh_degree, mode="RGB+D", background=None):
        return rasterization_2dgs(
            means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
            opacities=torch.sigmoid(splats["opacities"]), colors=torch.cat([splats["sh0"], splats["shN"]], 1),
            viewmats=sel_view, Ks=K, width=W, height=H, sh_degree=sh_degree, near_plane=0.2, far_plane=200.0,
            render_mode=mode, distloss=True,
            backgrounds=(bg if background is None else background)[None].expand(len(sel_view), 3))

    if a.mesh_only is not None:
        saved = torch.load(os.path.join(a.out, f"splats_{a.mesh_only}.pt"), map_location=dev)
        splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in saved.items()})
    os.makedirs(a.out, exist_ok=True)
    t_loop = time.perf_counter()
    for step in range(a.iterations if a.mesh_only is None else 0):
        i = int(torch.randint(len(ex.train), (1,)))
        deg = min(step // 1000, 3)
        step_bg = torch.rand(3, device=dev) if masks is not None else None
        colors, alphas, normals, normals_d, distort, median, info = render(viewmats[i:i + 1], Ks[i:i + 1], deg,
                                                                           background=step_bg)
        rgb = colors[..., :3]
        strategy.step_pre_backward(splats, opts, state, step, info)
        gt = images[i:i + 1]
        if masks is not None:
            gt = gt * masks[i:i + 1] + step_bg * (1 - masks[i:i + 1])
        loss = 0.8 * (rgb - gt).abs().mean() + 0.2 * (1 - _ssim(rgb.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2)))
        if step > 7000:
            nd = (normals_d * alphas.detach())
            loss = loss + 0.05 * (1 - (normals * nd).sum(-1)).mean()
        if step > 3000:
            loss = loss + 0.01 * distort.mean()
        loss.backward()
        strategy.step_post_backward(splats, opts, state, step, info, packed=False)
        if 0 < step < strategy.refine_stop_iter and step % strategy.reset_every == 0:
            reset_opa(params=splats, optimizers=opts, state=state, value=reset_value)  # what 1.5.3 means to do
        for o in opts.values():
            o.step()
            o.zero_grad(set_to_none=True)
        sched.step()
        if step + 1 in a.save_at:
            torch.save({k: v.detach() for k, v in splats.items()}, os.path.join(a.out, f"splats_{step + 1}.pt"))
        if (step + 1) % 1000 == 0:
            print(f"step {step + 1}/{a.iterations}: {len(splats['means'])} splats, "
                  f"{(step + 1) / (time.perf_counter() - t_loop):.1f} it/s", flush=True)

    with torch.no_grad():
        frames = []
        for j, i in enumerate(ex.train):
            colors, alphas, *_, median, _ = render(viewmats[j:j + 1], Ks[j:j + 1], 3)
            d = median[0, ..., 0].clone()
            d[alphas[0, ..., 0] < 0.5] = 0
            frames.append((colors[0, ..., :3].cpu().numpy(), d.cpu().numpy(), ex.K[i], ex.w2c[i]))
        mesh = tsdf_mesh(frames)
        run = clock.stop()
        vt = torch.tensor(ex.w2c[ex.test], dtype=torch.float32, device=dev)
        kt = torch.tensor(ex.K[ex.test], dtype=torch.float32, device=dev)
        renders = [render(vt[j:j + 1], kt[j:j + 1], 3)[0][0, ..., :3].clamp(0, 1).cpu().numpy() for j in range(len(vt))]
    it = a.iterations if a.mesh_only is None else a.mesh_only
    if a.mesh_only is not None:
        run = {"wall_s": None}  # an earlier run's training time is not known here
    run.update({"iterations": it, "surfels": int(len(splats["means"])),
                "recipe": "gsplat simple_trainer_2dgs (normal 0.05 > 7k, dist 0.01 > 3k), DefaultStrategy "
                          f"(prune_opa 0.05, opacity reset to {reset_value:g} every 3k)"
                          + (", random background outside the masks" if masks is not None else "") + ", 2DGS TSDF"})
    system = "gsplat 2DGS" if it == 30_000 else f"gsplat 2DGS ({it:,} it.)"
    write_result(a.out, system=system, mesh=mesh, renders=np.stack(renders), run=run)


if __name__ == "__main__":
    main()
