# SPDX-License-Identifier: Apache-2.0
"""How far a silhouette of surfels placed exactly on the truth reaches past the truth's (#59; design/decisions.md,
"Open: wtopo's meshes lie inside the surface").

    .venv/bin/python lab/silhouette_excess.py [SCENE ...]          (FUSION_ONLY=1: the fusion of the true depths only)

For each lab/hard.py SCENE (default blob_flat): surfels sampled evenly on the true surface (spacing and in-plane
standard deviation in pixel footprints at the object's distance, the normals the faces'), rendered from four
training views. The silhouette's outward shift is the rendered alpha's sum minus the true mask's, over the mask's
boundary pixels [px]: what the fit's photometric and mask terms pull the surface in against. Rendered by the kernel
(``wtopo.ops.rasterize_surfels``) and, in a band of pixels around the boundary, by the brute-force reference
(``tests/reference/rasterize.py``) as is and with the filter branch's opacity scaled by Mip-Splatting's amplitude
``sqrt(det S / det(S + sigma^2 I))`` (S: the surfel's projected covariance [px^2]); exact for Mip-Splatting's
convolved footprint, an approximation for this rasterizer's max of the surfel's Gaussian and the filter's (an edge-on
surfel loses all of its filter branch). First fuses the scene's true depth maps as the final fusion does (the CPU
plan's grid and truncation, a narrower truncation, a finer grid), with lab/suite_signed.py's offsets: what the fusion
itself adds. Nothing imports it.
"""

import inspect
import os
import sys

import numpy as np
import torch
import trimesh
from scipy.ndimage import binary_dilation, binary_erosion

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
from reference import rasterize as ref  # noqa: E402

import hard  # noqa: E402
from signed_error import TruthPlanes  # noqa: E402
from suite_signed import SAMPLES  # noqa: E402
from wtopo import ops  # noqa: E402
from wtopo.fitting.tsdf import FusionBounds, fuse_depths  # noqa: E402

VIEWS = 4
CASES = [(1.0, 1.2, 0.9), (0.5, 0.7, 0.9)]  # (spacing, in-plane std [px], opacity)

# the reference with the filter branch's alpha scaled per surfel by GAIN (its one alpha line patched)
_SRC = inspect.getsource(ref.rasterize_reference).replace(
    "alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * rho), max=0.99)",
    "alpha = torch.clamp(opacities[None] * torch.where(b3, torch.ones_like(rho), GAIN[None]) * torch.exp(-0.5 * rho),"
    " max=0.99)")
assert "GAIN" in _SRC
_NS = dict(ref.__dict__)
exec(_SRC, _NS)


def quats_from_normals(n: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) turning +z onto each normal."""
    w = 1.0 + n[:, 2]
    q = np.stack([w, -n[:, 1], n[:, 0], np.zeros(len(n))], 1)  # (1 + z.n, z x n)
    q[w < 1e-6] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def coverage_gain(cam, pts, quats, std_world, sigma) -> np.ndarray:
    """Mip-Splatting's amplitude of each surfel's footprint widened by the filter: sqrt(det S / det(S + s^2 I))."""
    tu, tv, _ = ref.quat_axes_ref(torch.as_tensor(quats))
    rm, t, f = np.asarray(cam.R), np.asarray(cam.t), float(cam.K[0, 0])
    pc = pts @ rm.T + t
    z = pc[:, 2:3]
    cols = []
    for ax in (tu.numpy(), tv.numpy()):
        a = (ax * std_world) @ rm.T
        cols.append(f * (a[:, :2] / z - pc[:, :2] * a[:, 2:3] / z ** 2))
    jac = np.stack(cols, -1)
    s = jac @ jac.transpose(0, 2, 1)
    return np.sqrt(np.clip(np.linalg.det(s), 0, None) / np.linalg.det(s + sigma ** 2 * np.eye(2)))


def excess(scene, pts, quats, std_world, op, sigma, how) -> float:
    """Mean outward shift of the rendered silhouette over VIEWS views [px]; ``how``: kernel, reference or gain."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64 if how != "kernel" else torch.float32)  # noqa: E731
    n = len(pts)
    means, q, sc = t(pts), t(quats), t(np.full((n, 2), std_world))
    opv, col = t(np.full(n, op)), t(np.full((n, 3), 0.5))
    shifts = []
    for v in range(VIEWS):
        cam = scene.cameras[v]
        m = np.asarray(scene.masks[v], bool)
        per = (m & ~binary_erosion(m)).sum()
        if how == "kernel":
            a = ops.rasterize_surfels(means, q, sc, opv, col, cam, config=ops.RasterConfig(filter_sigma=sigma)).alpha
            shifts.append((float(a.sum()) - m.sum()) / per)
            continue
        band = binary_dilation(m, iterations=3) & ~binary_erosion(m, iterations=3)  # alpha is 0 or saturated beyond
        idx = torch.as_tensor(np.flatnonzero(band.reshape(-1)))
        pc = pts @ np.asarray(cam.R).T + np.asarray(cam.t)
        uv = (pc[:, :2] / pc[:, 2:3]) @ np.asarray(cam.K)[:2, :2].T + np.asarray(cam.K)[:2, 2]
        ij = np.clip(np.floor(uv).astype(int), 0, [cam.width - 1, cam.height - 1])
        sel = np.flatnonzero(binary_dilation(band, iterations=8)[ij[:, 1], ij[:, 0]])  # the surfels that reach it
        _NS["GAIN"] = torch.as_tensor(coverage_gain(cam, pts[sel], quats[sel], std_world, sigma) if how == "gain"
                                      else np.ones(len(sel)))
        acc = np.concatenate([
            _NS["rasterize_reference"](means[sel], q[sel], sc[sel], opv[sel], col[sel], cam, near=1e-3, far=1e3,
                                       pixels=idx[c:c + 256], filter_sigma=sigma)["alpha"].numpy()
            for c in range(0, len(idx), 256)])
        shifts.append((acc.sum() - m.reshape(-1)[idx.numpy()].sum()) / per)
    return float(np.mean(shifts))


def main(names: list[str]) -> None:
    torch.set_grad_enabled(False)
    for name in names or ["blob_flat"]:
        scene, gt, _ = hard._build(name)
        cam = scene.cameras[0]
        px = float(np.linalg.norm(cam.center - gt.centroid)) / float(cam.K[0, 0])  # a pixel footprint [world]
        diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
        print(f"{name}: a pixel footprint is {px / diag * 100:.3f} % of the diagonal")
        lo, hi = gt.bounds
        side = float(np.max(hi - lo))
        lo, hi = lo - 0.05 * side, hi + 0.05 * side
        planes = TruthPlanes(gt, SAMPLES[0])
        for res, trunc in ((126, 4), (126, 2), (252, 4)):  # about the CPU plan's grid and truncation, then not
            voxel = side * 1.1 / res
            m = fuse_depths(scene.cameras, [np.asarray(d, np.float32) for d in scene.depths],
                            [np.asarray(c, np.float32) for c in scene.images],
                            FusionBounds(lo, hi, voxel, trunc * voxel))
            s = planes.offsets(m, SAMPLES[1])
            print(f"  the true depths fused at {res}, truncated at {trunc} voxels: mean offset {s.mean():+.4f} % of "
                  f"the diagonal, {(s < 0).mean() * 100:.0f} % inside, mean unsigned {np.abs(s).mean():.4f} %")
        if os.environ.get("FUSION_ONLY"):
            continue
        for spacing, std, op in CASES:
            pts, fi = trimesh.sample.sample_surface_even(gt, int(gt.area / (spacing * px) ** 2), seed=0)
            quats = quats_from_normals(gt.face_normals[fi])
            row = [f"  {len(pts)} surfels, spacing {spacing} px, std {std} px, opacity {op}:"]
            for sigma, how in [(0.35, "kernel"), (0.35, "reference"), (0.35, "gain"), (0.15, "kernel"),
                               (0.05, "kernel")]:
                row.append(f"{how} {sigma} px {excess(scene, pts, quats, std * px, op, sigma, how):+.3f}")
            print(", ".join(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
