"""Lab (nothing imports it): background shells seeded only where the stereo found nothing.

The background shells (wtopo.fitting.background) are seeded along random pixels of random training views. On
DTU they cost 11 dB in held-out view 40 (benchmarks/peers.md): shell surfels painted with the near table's white
show through the black backdrop. Here a pixel seeds a shell only when no confirmed stereo point (all of them,
before the thinning to init.num_points) projects within RADIUS_PX of it in that view, so the shells stand in
only for what the stereo did not find (sky, distant blocks, untextured backdrop).

    python lab/shell_seeds.py run_wtopo EXCH OUT [run_wtopo.py arguments]   # the peers harness's wtopo run
    python lab/shell_seeds.py fit SCENE OUT [--set KEY=VALUE ...]            # a built-in scene, wtopo.fit
"""
import os
import sys

import numpy as np
import torch

RADIUS_PX = 2  # a stereo point covers the pixels within this many pixels of its projection
HERE = os.path.dirname(os.path.abspath(__file__))
FOUND = {}


def patch():
    from wtopo.fitting import background as B
    from wtopo.fitting import loop as L
    from wtopo.geometry import mvs

    real_sweep = mvs.plane_sweep_points

    def sweep(*a, **k):
        out = real_sweep(*a, **k)
        FOUND["points"] = np.asarray(out.points)
        return out

    mvs.plane_sweep_points = sweep
    real_bg = B.background_surfels

    def seeded(scene, layout, n, *, sh_degree, opacity, device, generator):
        pts = FOUND.get("points")
        if pts is None or len(pts) == 0:
            return real_bg(scene, layout, n, sh_degree=sh_degree, opacity=opacity, device=device, generator=generator)
        free = []  # per view: a boolean [H, W] of pixels no stereo point covers
        for cam in scene.cameras:
            uv, z = cam.project(pts)
            ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
            c = np.floor(uv[ok]).astype(int)
            cov = np.zeros((cam.height, cam.width), bool)
            for dy in range(-RADIUS_PX, RADIUS_PX + 1):
                for dx in range(-RADIUS_PX, RADIUS_PX + 1):
                    x, y = c[:, 0] + dx, c[:, 1] + dy
                    m = (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
                    cov[y[m], x[m]] = True
            free.append(~cov)
        frac = float(np.mean([f.mean() for f in free]))
        print(f"shell seeds: {frac:.1%} of the training pixels have no stereo point", flush=True)
        if frac == 0.0:
            return real_bg(scene, layout, n, sh_degree=sh_degree, opacity=opacity, device=device, generator=generator)
        # background_surfels' geometry, its pixels drawn from the free ones (views weighted by their free count)
        from wtopo.fitting.surfels import Surfels

        counts = np.array([f.sum() for f in free], dtype=np.float64)
        rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, (1,), generator=generator)))
        view = rng.choice(len(free), size=n, p=counts / counts.sum())
        radii = B.shell_radii(layout)
        c0 = layout.roi_center
        images = scene.images.detach().cpu().numpy()
        shell = np.arange(n) % len(radii)
        pts, cols, nrm, scale = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
        for i in np.unique(view):
            sel = np.nonzero(view == i)[0]
            cam = scene.cameras[i]
            rows, colsi = np.nonzero(free[i])
            pick = rng.integers(0, len(rows), size=len(sel))
            r_i, c_i = rows[pick], colsi[pick]
            _, rays = cam.pixel_rays("cpu", torch.float64)
            d = rays[r_i, c_i].numpy()
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            oc = cam.center - c0
            b = d @ oc
            r = radii[shell[sel]]
            t = -b + np.sqrt(np.maximum(b * b - (oc @ oc - r * r), 0.0))
            pts[sel] = cam.center + t[:, None] * d
            cols[sel] = images[i][r_i, c_i]
            nrm[sel] = -d
            scale[sel] = B._FOOTPRINT_PIXELS * t / float(cam.K[0, 0])
        tt = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
        return Surfels.from_points(tt(pts), tt(cols), scales=tt(scale), normals=tt(nrm), opacity=opacity,
                                   sh_degree=sh_degree, generator=generator)

    L.background_surfels = seeded


def main():
    mode = sys.argv[1]
    patch()
    if mode == "run_wtopo":
        sys.path.insert(0, os.path.join(HERE, "..", "benchmarks", "peers"))
        import run_wtopo
        run_wtopo.main(sys.argv[2:] + ["--label", "wtopo (shells on stereo-free pixels)"])
    else:
        from wtopo.cli import main as cli
        sys.argv = ["wtopo", "fit", sys.argv[2], "--out", sys.argv[3], *sys.argv[4:]]
        cli()


if __name__ == "__main__":
    main()
