"""Lab (nothing imports it): background shells kept only where the training views agree on their colour.

DTU's held-out view 40 loses 1-7 dB to the background shells (benchmarks/peers.md): a shell surfel seeded from a
pixel of the near table that the stereo did not confirm sits far beyond the cameras, where other views see it in
directions the photographs show the black backdrop. A shell that stands in for a truly distant background (sky,
far hills) projects, in every other view whose pixel there is also free of stereo points, onto the same colour;
one that stands in for near content does not. This patch seeds twice the shells the package would
(wtopo.fitting.background.background_surfels) and keeps those whose colour agrees (max channel difference below
TOLERANCE) with at least AGREE of the free pixels they project to over the training views, when at least MIN_VIEWS
views see them free (fewer: kept, nothing says otherwise); then the package's count of them.

    python lab/shell_consistency.py run_wtopo EXCH OUT [run_wtopo.py arguments]
"""
import os
import sys

import numpy as np
import torch

TOLERANCE = 0.15  # colour agreement, max channel (the unbounded scenes vary exposure by +-10 %)
AGREE = 0.5  # share of the free views that must agree
MIN_VIEWS = 3  # free views needed to judge a shell
HERE = os.path.dirname(os.path.abspath(__file__))


def consistent(means: np.ndarray, colors: np.ndarray, cameras, images: np.ndarray, free) -> np.ndarray:
    """Boolean [N]: the shell's colour agrees with the free pixels it projects to (see the module docstring)."""
    agree = np.zeros(len(means))
    seen = np.zeros(len(means))
    for cam, img, fr in zip(cameras, images, free):
        uv, z = cam.project(means)
        x, y = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
        idx = np.flatnonzero(ok)
        idx = idx[fr[y[idx], x[idx]]]  # a stereo point covers the pixel: a nearer surface hides the shell there
        seen[idx] += 1
        diff = np.abs(img[y[idx], x[idx]] - colors[idx]).max(axis=1)
        agree[idx] += diff < TOLERANCE
    return (seen < MIN_VIEWS) | (agree >= AGREE * np.maximum(seen, 1))


def patch():
    from wtopo.fitting import background as B
    from wtopo.fitting import loop as L
    from wtopo.fitting.surfels import Surfels

    real = B.background_surfels

    def filtered(scene, layout, n, *, sh_degree, opacity, device, generator, covered_by=None):
        bg = real(scene, layout, 2 * n, sh_degree=sh_degree, opacity=opacity, device=device, generator=generator,
                  covered_by=covered_by)
        if bg is None:
            return bg
        cams = scene.cameras
        if covered_by is not None and len(covered_by):
            free = [f.cpu().numpy() for f in B.uncovered_pixels(cams, covered_by, device, generator)]
        else:
            free = [np.ones((c.height, c.width), bool) for c in cams]
        means = bg.means.detach().cpu().double().numpy()
        colors = (bg.params["sh_dc"].detach()[:, 0].cpu().double().numpy() * 0.28209479177387814 + 0.5)
        keep = consistent(means, colors, cams, scene.images.detach().cpu().numpy(), free)
        idx = np.flatnonzero(keep)
        print(f"shell consistency: {len(idx)} of {len(keep)} seeds agree across the views", flush=True)
        if len(idx) > n:
            idx = np.sort(np.random.default_rng(0).choice(idx, n, replace=False))
        p, _ = bg.take(torch.as_tensor(idx, device=bg.means.device))
        return Surfels(**p)

    L.background_surfels = filtered


def main():
    mode = sys.argv[1]
    patch()
    if mode != "run_wtopo":
        raise SystemExit("usage: lab/shell_consistency.py run_wtopo EXCH OUT [run_wtopo.py arguments]")
    sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))
    import run_wtopo
    run_wtopo.main(sys.argv[2:] + ["--label", "wtopo (consistent shells)"])


if __name__ == "__main__":
    main()
