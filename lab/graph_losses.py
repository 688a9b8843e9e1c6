# SPDX-License-Identifier: Apache-2.0
"""Whether the fit's per-pixel loss terms run as CUDA graphs, and what it saves (#60's loop; a lab experiment).

DTU's views are 384 x 384: the loss terms' kernels take tens of microseconds and their section (2.3 ms an
iteration) is host time: torch operations, Warp launches, autograd nodes. Here the late-stage terms of
``Objective`` (photometric, mask, normal consistency against the depth normals, distortion) run on random render
outputs of that size, eagerly and through ``torch.cuda.make_graphed_callables`` (a forward graph and a backward
graph, inputs copied into static buffers), with the Warp ops on torch's capture stream. Prints the host time per
forward + backward of each, the wall time per call pipelined, and whether losses and gradients agree.

    python3 lab/graph_losses.py [--size 384] [--calls 300]
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch
import warp as wp

import wtopo
from wtopo import _bridge
from wtopo.depth_normals import depth_normals
from wtopo.fitting.losses import distortion, mask_loss, normal_consistency
from wtopo.photometric import photometric_loss


@contextlib.contextmanager
def _on_torch_stream_no_sync(wdev, device):
    """The bridge's scope without Warp's event wait on its previous stream (illegal inside a stream capture)."""
    with wp.ScopedDevice(wdev):
        if wdev.is_cuda:
            with wp.ScopedStream(_bridge._warp_stream(device), sync_enter=False):  # noqa: SLF001
                yield
        else:
            yield


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--calls", type=int, default=300)
    a = ap.parse_args()
    dev = torch.device("cuda:0")
    _bridge._on_torch_stream = _on_torch_stream_no_sync  # noqa: SLF001
    g = torch.Generator(device=dev).manual_seed(0)
    H = W = a.size
    cam = wtopo.Camera.look_at([0, 0, -3.0], [0, 0, 0], [0, -1, 0], fov_x=0.7, width=W, height=H)
    o, d = cam.pixel_rays(dev)

    def leaf(*shape, lo=0.0, hi=1.0):
        return (torch.rand(*shape, generator=g, device=dev) * (hi - lo) + lo).requires_grad_()

    rgb, alpha, dist = leaf(H, W, 3), leaf(H, W, lo=0.05, hi=0.95), leaf(H, W, hi=0.01)
    normal = torch.nn.functional.normalize(torch.randn(H, W, 3, generator=g, device=dev), dim=-1).requires_grad_()
    median = leaf(H, W, lo=2.5, hi=3.5).detach()  # the fit's normal term holds the depth normals fixed
    image = torch.rand(H, W, 3, generator=g, device=dev)
    mask = torch.rand(H, W, generator=g, device=dev) > 0.3

    def terms(rgb, alpha, normal, dist, median):
        covered = alpha.detach() >= 0.5
        dn, dmask = depth_normals(median.detach(), o, d, covered)
        return torch.stack([photometric_loss(rgb, image, dssim=0.2), 0.1 * mask_loss(alpha, mask.float()),
                            0.05 * normal_consistency(normal, dn, alpha, dmask), 100.0 * distortion(dist)])

    leaves = (rgb, alpha, normal, dist, median)

    def run(fn):
        for t in leaves[:4]:
            t.grad = None
        out = fn(*leaves)
        out.sum().backward()
        return out.detach().clone(), [t.grad.clone() for t in leaves[:4]]

    with wtopo._validate.trusted_values():  # noqa: SLF001 - the fit's terms run trusted
        ref = run(terms)
        graphed = torch.cuda.make_graphed_callables(terms, leaves, num_warmup_iters=3)
        got = run(graphed)
        print("losses eager", ref[0].tolist(), "graphed", got[0].tolist())
        print("max |grad difference|", max(float((x - y).abs().max()) for x, y in zip(ref[1], got[1])))
        for name, fn in (("eager", terms), ("graphed", graphed)):
            for _ in range(10):
                run(fn)
            torch.cuda.synchronize()
            host = 0.0
            t0 = time.perf_counter()
            for _ in range(a.calls):
                s = time.perf_counter()
                out = fn(*leaves)
                out.sum().backward()
                host += time.perf_counter() - s
                for t in leaves[:4]:
                    t.grad = None
            torch.cuda.synchronize()
            wall = time.perf_counter() - t0
            print(f"{name}: host {1e3 * host / a.calls:.3f} ms, wall {1e3 * wall / a.calls:.3f} ms per forward + "
                  f"backward ({H} x {W})")


if __name__ == "__main__":
    main()
