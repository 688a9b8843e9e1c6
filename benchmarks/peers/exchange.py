# SPDX-License-Identifier: Apache-2.0
"""The exchange folder every system of the peers benchmark reads: one scene, one split, one frame.

``export(scene, out)`` writes a :class:`wtopo.Scene` (any loader or built-in scene) so that wtopo and
every peer see the same images, masks, cameras, held-out views and initial points:

* ``meta.json``: size, split, whether the capture is masked, the similarity back to the scene's
  frame, where the initial points came from, and for a scene with a region of interest
  (``scene.info["roi"]``: the unbounded synthetic scenes) that box (``roi``, normalised frame): the
  ROI F-score is taken over it;
* ``cameras.npz``: ``K`` [N, 3, 3] and ``w2c`` [N, 4, 4] (OpenCV axes) in the normalised frame;
* ``images/NNNN.png`` (every view), ``masks/NNNN.png`` (masked captures), ``gt.ply`` (when the
  scene has a ground-truth mesh, normalised frame), ``points.npz`` (initial points, colours);
* ``colmap/``: the training views as an undistorted COLMAP text model (``images/``,
  ``sparse/0/{cameras,images,points3D}.txt``), which the 3DGS-family peers read.

The 3DGS-family rasterizers ignore the principal point, so every image is cropped until the principal
point sits at its centre (to within a quarter pixel on a shared lens); ``K`` is the exact cropped lens.
"""

from __future__ import annotations

import json
import os

import numpy as np
import torch
from PIL import Image

__all__ = ["centred_crop", "export", "load", "Exchange"]


def centred_crop(K: np.ndarray, width: int, height: int) -> tuple[int, int, np.ndarray, np.ndarray]:
    """Crop size and per-view offsets that put each view's principal point at the crop's centre.

    Args:
        K: intrinsics, [N, 3, 3] float, pixel centres at +0.5.
        width: image width [px].
        height: image height [px].

    Returns:
        ``(w, h, x0, y0)``: the common crop size [px] and the integer offsets [N] of its corner.
    """
    def axis(c: np.ndarray, size: int) -> tuple[int, np.ndarray]:
        half = float(np.min(np.minimum(c, size - c)))
        best = None
        for n in range(int(np.floor(2 * half)), max(int(np.floor(2 * half)) - 4, 1), -1):
            o = np.round(c - n / 2)
            o = np.clip(o, 0, size - n)
            res = float(np.max(np.abs(c - o - n / 2)))
            if best is None or res < best[0] - 1e-9:
                best = (res, n, o.astype(np.int64))
        if best is None:
            raise ValueError(f"the principal point {c.tolist()} leaves no crop inside a {size}-px image")
        return best[1], best[2]

    w, x0 = axis(K[:, 0, 2], width)
    h, y0 = axis(K[:, 1, 2], height)
    return w, h, x0, y0


def _qvec(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternion (w, x, y, z) of a rotation matrix."""
    q = np.empty(4)
    t = np.trace(R)
    if t > 0:
        s = 0.5 / np.sqrt(t + 1.0)
        q[:] = 0.25 / s, (R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s, (R[1, 0] - R[0, 1]) * s
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    return q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)


def _initial_points(scene, n_random: int, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """The peers' initial points (normalised frame): the scene's own (SfM), else stereo, else random."""
    if scene.points is not None and len(scene.points):
        pts = np.asarray(scene.points, dtype=np.float64)
        col = (np.asarray(scene.point_colors, dtype=np.float64) if scene.point_colors is not None
               else np.full_like(pts, 0.5))
        return pts, col, "scene"
    lo, hi = (np.asarray(b, dtype=np.float64) for b in scene.region_of_interest())
    if scene.background is None:  # a real capture: what SfM/MVS would give, from the images alone
        from wtopo.geometry.mvs import plane_sweep_points
        train = scene.split("train")
        near = 0.05 * float(np.linalg.norm(hi - lo))
        dev = "cuda" if torch.cuda.is_available() else "cpu"
        mvs = plane_sweep_points(train.cameras, train.images.to(dev), lo, hi, near=near, device=dev)
        if len(mvs.points) >= 1000:
            pts = np.asarray(mvs.points, dtype=np.float64)
            col = np.asarray(mvs.colors, dtype=np.float64)
            if len(pts) > n_random:
                pick = np.random.default_rng(seed).choice(len(pts), n_random, replace=False)
                pts, col = pts[pick], col[pick]
            return pts, col, "stereo"
    rng = np.random.default_rng(seed)  # 3DGS/2DGS's recipe for synthetic objects: random in the box
    pts = lo + (hi - lo) * rng.random((n_random, 3))
    return pts, rng.random((n_random, 3)), "random"


def export(scene, out: str, *, test_every: int = 8, n_points: int = 100_000, seed: int = 0) -> dict:
    """Write ``scene`` as an exchange folder (module docstring); returns ``meta``.

    Held-out views: the scene's ``test_indices`` when it has them, else every ``test_every``-th view
    (index 0, 8, 16, ...: the 3DGS ``llffhold`` convention).
    """
    if scene.test_indices is not None and len(scene.test_indices):
        test = sorted(int(i) for i in scene.test_indices)
        train = (sorted(int(i) for i in scene.train_indices) if scene.train_indices is not None
                 else [i for i in range(len(scene)) if i not in set(test)])
    else:
        test = list(range(0, len(scene), test_every))
        train = [i for i in range(len(scene)) if i % test_every]
    sim = scene.normalization()
    norm = scene.normalized()
    norm = type(norm)(**{**{k: getattr(norm, k) for k in ("cameras", "images", "masks", "gt_mesh", "bounds",
                                                           "points", "point_colors", "background", "name")},
                         "train_indices": train, "test_indices": test})
    K = np.stack([np.asarray(c.K, dtype=np.float64) for c in norm.cameras])
    w2c = np.stack([np.asarray(c.world_to_camera, dtype=np.float64) for c in norm.cameras])
    if any(c.distortion is not None and np.any(np.asarray(c.distortion) != 0) for c in norm.cameras):
        raise ValueError("the peers read undistorted images only: undistort the capture first")
    W, H = norm.width, norm.height
    w, h, x0, y0 = centred_crop(K, W, H)
    Kc = K.copy()
    Kc[:, 0, 2] -= x0
    Kc[:, 1, 2] -= y0
    os.makedirs(os.path.join(out, "images"), exist_ok=True)
    images = norm.images.detach().cpu().numpy() if isinstance(norm.images, torch.Tensor) else np.asarray(norm.images)
    masks = None
    if norm.masks is not None:
        masks = norm.masks.detach().cpu().numpy() if isinstance(norm.masks, torch.Tensor) else np.asarray(norm.masks)
        os.makedirs(os.path.join(out, "masks"), exist_ok=True)
    for i in range(len(norm)):
        crop = np.s_[y0[i]:y0[i] + h, x0[i]:x0[i] + w]
        Image.fromarray(np.round(np.clip(images[i][crop], 0, 1) * 255).astype(np.uint8)).save(
            os.path.join(out, "images", f"{i:04d}.png"))
        if masks is not None:
            m8 = (masks[i][crop] > 0).astype(np.uint8) * 255
            Image.fromarray(m8).save(os.path.join(out, "masks", f"{i:04d}.png"))
    np.savez(os.path.join(out, "cameras.npz"), K=Kc, w2c=w2c)
    if norm.gt_mesh is not None:
        norm.gt_mesh.export(os.path.join(out, "gt.ply"))
    pts, col, kind = _initial_points(norm, n_points, seed)
    np.savez(os.path.join(out, "points.npz"), points=pts.astype(np.float32), colors=col.astype(np.float32))
    _write_colmap(os.path.join(out, "colmap"), os.path.join(out, "images"), Kc, w2c, w, h, train, pts, col)
    meta = {"name": scene.name or os.path.basename(os.path.normpath(out)), "width": int(w), "height": int(h),
            "train": train, "test": test, "masked": masks is not None,
            "background": None if norm.background is None else [float(v) for v in norm.background],
            "points": kind, "gt": norm.gt_mesh is not None,
            "to_world": {"scale": float(sim.scale), "translation": [float(v) for v in sim.translation]},
            "crop": {"x0": x0.tolist(), "y0": y0.tolist(), "source_size": [int(W), int(H)]}}
    roi = scene.info.get("roi")
    if roi is not None:
        meta["roi"] = [np.asarray(sim.to_internal(np.asarray(b, np.float64))).tolist() for b in roi]
    with open(os.path.join(out, "meta.json"), "w") as f:
        json.dump(meta, f, indent=1)
    return meta


def _write_colmap(root: str, images: str, K, w2c, w: int, h: int, train: list[int], pts, col) -> None:
    """Training views as a PINHOLE COLMAP text model (one camera per view; sorted names keep the order)."""
    os.makedirs(os.path.join(root, "sparse", "0"), exist_ok=True)
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    cams, imgs = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"], ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"]
    for j, i in enumerate(train, start=1):
        name = f"{i:04d}.png"
        dst = os.path.join(root, "images", name)
        if not os.path.exists(dst):
            os.link(os.path.join(images, name), dst)
        fx, fy, cx, cy = (float(v) for v in (K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]))
        cams.append(f"{j} PINHOLE {w} {h} {fx!r} {fy!r} {cx!r} {cy!r}")
        q, t = _qvec(w2c[i, :3, :3]), w2c[i, :3, 3]
        imgs.append(f"{j} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {j} {name}")
        imgs.append("")  # no 2D points
    c8 = np.round(np.clip(col, 0, 1) * 255).astype(int)
    lines = ["# POINT3D_ID X Y Z R G B ERROR TRACK[]"]
    lines += [f"{k + 1} {p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {c[0]} {c[1]} {c[2]} 0"
              for k, (p, c) in enumerate(zip(pts, c8))]
    for name, body in (("cameras.txt", cams), ("images.txt", imgs), ("points3D.txt", lines)):
        with open(os.path.join(root, "sparse", "0", name), "w") as f:
            f.write("\n".join(body) + "\n")


class Exchange:
    """An exchange folder read back: cameras, images, masks, split, ground truth (normalised frame)."""

    def __init__(self, root: str):
        self.root = root
        with open(os.path.join(root, "meta.json")) as f:
            self.meta = json.load(f)
        cams = np.load(os.path.join(root, "cameras.npz"))
        self.K, self.w2c = cams["K"], cams["w2c"]
        self.width, self.height = self.meta["width"], self.meta["height"]
        self.train, self.test = self.meta["train"], self.meta["test"]
        self.masked = bool(self.meta["masked"])

    def __len__(self) -> int:
        return len(self.K)

    def image(self, i: int) -> np.ndarray:
        """View ``i``'s colours, [H, W, 3] float32 in [0, 1]."""
        return np.asarray(Image.open(os.path.join(self.root, "images", f"{i:04d}.png")).convert("RGB"),
                          dtype=np.float32) / 255

    def mask(self, i: int) -> np.ndarray | None:
        """View ``i``'s foreground mask, [H, W] bool, or ``None``."""
        if not self.masked:
            return None
        return np.asarray(Image.open(os.path.join(self.root, "masks", f"{i:04d}.png"))) > 127

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        p = np.load(os.path.join(self.root, "points.npz"))
        return p["points"], p["colors"]

    def gt(self):
        """The ground-truth mesh (normalised frame) or ``None``."""
        import trimesh
        path = os.path.join(self.root, "gt.ply")
        return trimesh.load(path, process=False) if os.path.exists(path) else None

    def roi(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The region of interest ``(lower [3], upper [3])`` (normalised frame) or ``None``."""
        roi = self.meta.get("roi")
        return None if roi is None else (np.asarray(roi[0], np.float64), np.asarray(roi[1], np.float64))

    def camera(self, i: int):
        from wtopo import Camera
        return Camera(K=self.K[i], world_to_camera=self.w2c[i], width=self.width, height=self.height,
                      name=f"{i:04d}")

    def scene(self):
        """A :class:`wtopo.Scene` of every view with the split (initial points only when the scene had its own)."""
        import wtopo
        images = np.stack([self.image(i) for i in range(len(self))])
        masks = np.stack([self.mask(i) for i in range(len(self))]) if self.masked else None
        pts = col = None
        if self.meta["points"] == "scene":
            pts, col = self.points()
        bg = self.meta["background"]
        return wtopo.Scene(cameras=[self.camera(i) for i in range(len(self))], images=images, masks=masks,
                           gt_mesh=self.gt(), points=pts, point_colors=col,
                           background=None if bg is None else tuple(bg), name=self.meta["name"],
                           train_indices=self.train, test_indices=self.test)


def load(root: str) -> Exchange:
    return Exchange(root)
