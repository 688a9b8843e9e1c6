# SPDX-License-Identifier: Apache-2.0
"""The final mesh of a masked object moved along its normals until its silhouettes cover the training masks
(#59: wtopo's meshes lie inside the surface, design/decisions.md; bunny64's remaining gap to PGSR).

    SIL_OFFSET=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]

The surfels' low-pass silhouettes reach past the truth's, so the mask and photometric terms pull the surface in by
a fraction of a pixel. The mesh itself has no low-pass: ray cast from a training view, its silhouette should cover
that view's mask. Per view, (mask area - silhouette area) / the mask's perimeter is how far (in pixels) the mesh's
outline lies inside the mask's; times the footprint at the mesh's median depth (z / fx) it is a distance. The median
over the views whose mask stays off the image border moves every vertex along its normal (``SIL_OFFSET_GAIN``, 1 by
default, of it; at most ``SIL_OFFSET_MAX_PX`` footprints, 1 by default). Offline on GPU meshes (bunny64 at the CUDA
default): +0.163 px (views 0.128-0.193), Chamfer 0.0461 -> 0.0393 %; PGSR's own mesh -0.167 px, 0.0392 -> 0.0385.
Scenes without masks and scenes (not objects) are unchanged. ``install()`` patches ``FitRun._final_mesh``
(lab/fit_patches.py's SIL_OFFSET). Nothing in the product imports it.
"""

import os

import numpy as np
import torch


def silhouette_offset(verts: np.ndarray, faces: np.ndarray, cameras, masks) -> tuple[float, np.ndarray]:
    """``(distance, pixels)``: the median distance [the cameras' units] the mesh's outline lies inside the masks'
    (+: inside, grow), and each used view's offset in pixels. ``masks``: [H, W] per camera (>= 0.5 inside)."""
    from wtopo import ops

    v = torch.as_tensor(np.asarray(verts), dtype=torch.float32)
    f = torch.as_tensor(np.asarray(faces), dtype=torch.int32)
    dist, pix = [], []
    for cam, m in zip(cameras, masks):
        mk = (m.detach().cpu().numpy() if torch.is_tensor(m) else np.asarray(m)) >= 0.5
        if mk.sum() < 64 or mk[0].any() or mk[-1].any() or mk[:, 0].any() or mk[:, -1].any():
            continue  # the object is cut by the image border: its outline there is the frame's
        r = ops.raycast_mesh(v, f, cam)
        hit = r.mask.cpu().numpy().astype(bool)
        if hit.sum() < 64:
            continue
        edges = (mk[1:] != mk[:-1]).sum() + (mk[:, 1:] != mk[:, :-1]).sum()
        px = float(mk.sum() - hit.sum()) / (float(edges) * np.pi / 4)  # axis-aligned edges ~ 4/pi the length
        z = float(np.median(r.depth.cpu().numpy()[hit]))
        pix.append(px)
        dist.append(px * z / float(cam.K[0, 0]))
    if not dist:
        return 0.0, np.zeros(0)
    return float(np.median(dist)), np.asarray(pix)


def install() -> None:
    """Patch the fit so that a masked object's final mesh is moved onto its masks' outline."""
    from wtopo.fitting import loop

    gain = float(os.environ.get("SIL_OFFSET_GAIN", "1"))
    limit = float(os.environ.get("SIL_OFFSET_MAX_PX", "1"))
    final = loop.FitRun._final_mesh

    def offset_final_mesh(self):
        mesh = final(self)
        if getattr(self.cfg.final, "outline", False):  # the product moves it already (wtopo/geometry/outline.py)
            return mesh
        masks = self.train.masks
        if masks is None or self.plan.layout is None or self.plan.layout.kind.value == "scene" or len(mesh.faces) == 0:
            return mesh
        d, px = silhouette_offset(mesh.vertices, mesh.faces, self.train.cameras, masks)
        if len(px) == 0:
            return mesh
        med = float(np.median(px))
        scale = gain * min(1.0, limit / max(abs(med), 1e-12))
        moved = mesh.copy()  # keeps the vertex colours
        moved.vertices = np.asarray(mesh.vertices) + mesh.vertex_normals * (scale * d)
        self.record("silhouette_offset", pixels=round(med, 4), spread=[round(float(np.percentile(px, 10)), 4),
                    round(float(np.percentile(px, 90)), 4)], distance=d * scale, views=len(px))
        print(f"silhouette_offset: {med:+.3f} px over {len(px)} views (10-90 %: {np.percentile(px, 10):+.3f}.."
              f"{np.percentile(px, 90):+.3f}), moved {scale * d:+.3e}", flush=True)
        return moved

    loop.FitRun._final_mesh = offset_final_mesh
