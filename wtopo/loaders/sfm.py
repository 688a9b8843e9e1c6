# SPDX-License-Identifier: Apache-2.0
"""Camera poses for a folder of photographs: structure from motion with pycolmap, in process.

:func:`run_sfm` extracts SIFT features, matches them (every pair up to a few hundred images, each
image with its successors in name order for longer sets, as video frames), runs COLMAP's
incremental mapper with one camera shared by all images (``SIMPLE_RADIAL`` or ``OPENCV``; focal
length prior from the EXIF data when the photos carry it), refines the model by a last bundle
adjustment with a robust (Cauchy) loss and writes it as
``sparse/0/{cameras,images,points3D}.{bin,txt}`` beside the images, where a second run (and any
COLMAP tool) finds it. :func:`load_photos` reads the result with the COLMAP loader, so the
model's points seed the surfels, and undistorts the photos to pinhole cameras.

pycolmap is an optional dependency: ``pip install "wtopo[sfm]"`` (a 38 MB manylinux wheel with
CPU SIFT, matching and mapping).

Layout (``workspace``: the folder the images are in, its parent when that folder is called
``images`` or ``image``, or ``out_dir``)::

    workspace/database.db          features and matches (reused by a later run)
    workspace/sparse/0/            the model (text and binary)
    workspace/sparse/partial/      the largest model of a run that failed (too few images registered)
    workspace/sfm.json             what the run did: matcher and why, registered and dropped images, times

Modules (private; import from ``wtopo.loaders.sfm``): ``_sfm_options`` (options, result, error,
shared constants), ``_sfm_photos`` (finding the photographs, choosing the matcher, image sizes),
``_sfm_colmap`` (the pycolmap steps).
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings

from ._sfm_colmap import SFM_INSTALL_HINT as SFM_INSTALL_HINT  # noqa: F401  (was defined here)
from ._sfm_colmap import (
    _camera_dict,
    _extract,
    _map,
    _match,
    _names_list,
    _pycolmap,
    _quiet_colmap,
    _verified_partners,
    _why_dropped,
    _write_model,
)
from ._sfm_options import _MAX_NAMED, IMAGE_EXTENSIONS, SFM_SUMMARY, Matcher, SfMError, SfMOptions, SfMResult
from ._sfm_photos import _check_sizes, _pairs, _workspace, choose_matcher, find_photos

__all__ = ["IMAGE_EXTENSIONS", "Matcher", "SfMOptions", "SfMResult", "SfMError", "run_sfm", "load_photos",
           "find_photos", "choose_matcher"]


def _reuse(model_dir: str, workspace: str, image_dir: str, names: list[str]) -> SfMResult:
    from .colmap import read_model

    summary = os.path.join(workspace, SFM_SUMMARY)
    if os.path.isfile(summary):
        with open(summary) as fh:
            data = json.load(fh)
        data.update(model_dir=model_dir, workspace=workspace, image_dir=image_dir, reused=True)
        res = SfMResult(**{k: data[k] for k in SfMResult.__dataclass_fields__ if k in data})
    else:  # a model made by COLMAP itself
        cams, imgs, pts = read_model(model_dir)
        model, w, h, params = next(iter(cams.values()))
        reg = sorted(v[3] for v in imgs.values())
        camera = {"model": model, "width": w, "height": h, "params": list(params), "focal_prior": "unknown"}
        res = SfMResult(model_dir, workspace, image_dir, list(names), reg,
                        {n: "not in the existing model" for n in names if n not in set(reg)}, "unknown",
                        "the model was made elsewhere", camera, 0 if pts is None else len(pts[0]), None, {}, True)
    added = sorted(set(names) - set(res.images))
    if added:
        warnings.warn(f"{model_dir} was made from {len(res.images)} images; {len(added)} more are in {image_dir} now "
                      f"(e.g. {added[0]}) and are not used: delete {os.path.dirname(model_dir)} to redo the camera "
                      "poses", UserWarning, stacklevel=3)
    return res


def run_sfm(image_dir, *, out_dir=None, options: SfMOptions | None = None, reuse: bool = True,
            progress: bool = True) -> SfMResult:
    """Camera poses and sparse points for a folder of photographs (COLMAP through pycolmap, on the CPU).

    Steps, each with a progress bar: SIFT features (one camera shared by all images, focal prior
    from EXIF when present), matching (:func:`choose_matcher`: exhaustive up to a few hundred
    images, sequential beyond; the choice and its reason are printed), incremental mapping, then a
    global bundle adjustment with a Cauchy loss (:attr:`SfMOptions.robust_refinement`). The
    largest model is written as ``sparse/0`` in text and binary; unregistered images are named with
    the reason. Features and matches stay in ``database.db``, so a rerun after a failure only maps.

    Args:
        image_dir: folder of photographs (or a folder holding ``images/``); only
            :data:`IMAGE_EXTENSIONS` files count, sorted by name.
        out_dir: workspace for ``database.db``, ``sparse/`` and ``sfm.json``; default beside the
            images (their folder, or its parent when it is called ``images`` or ``image``). Give one for
            read-only image folders.
        options: :class:`SfMOptions` (default ones when ``None``).
        reuse: return an existing ``sparse/0`` of the workspace as it is instead of running.
        progress: print the matcher choice and show progress bars.

    Returns:
        :class:`SfMResult`; ``result.model_dir`` is the ``sparse/0`` folder.

    Raises:
        ModuleNotFoundError: pycolmap is missing (the message says ``pip install "wtopo[sfm]"``).
        FileNotFoundError: ``image_dir`` holds no photographs.
        ValueError: bad options (naming the field), fewer than 3 images, images of several sizes
            (listing them).
        SfMError: (a ``ValueError``) no overlap between the images, or fewer than
            :attr:`SfMOptions.min_registered_fraction` of them registered; the message says how
            many, which were dropped and why, and where the partial model was kept.

    Limitations:
        CPU only; one camera for all images (one lens and zoom setting, one image size). Images
        COLMAP cannot register are left out of the model, not guessed.

    References:
        J. L. Schoenberger and J.-M. Frahm, "Structure-from-Motion Revisited", CVPR 2016.
    """
    opts = SfMOptions() if options is None else options
    if not isinstance(opts, SfMOptions):
        raise TypeError(f"options must be a wtopo.loaders.sfm.SfMOptions or None, got {type(opts).__name__}")
    opts.validate()
    p = os.fspath(image_dir)
    if not os.path.isdir(p):
        raise FileNotFoundError(f"image_dir must be an existing folder, got {p!r}")
    found = find_photos(p)
    if found is None:
        raise FileNotFoundError(f"{p} holds no photographs (files ending in {', '.join(IMAGE_EXTENSIONS)}), nor does "
                                f"{os.path.join(p, 'images')}")
    img_dir, names = found
    workspace = os.fspath(out_dir) if out_dir is not None else _workspace(img_dir)
    model_dir = os.path.join(workspace, "sparse", "0")
    if reuse and any(os.path.isfile(os.path.join(model_dir, f"cameras.{e}")) for e in ("bin", "txt")):
        res = _reuse(model_dir, workspace, img_dir, names)
        if progress:
            print(f"wtopo sfm: reusing the camera poses in {model_dir} ({len(res.registered)} of "
                  f"{len(res.images)} images; delete {os.path.dirname(model_dir)} to redo them)")
        return res
    if len(names) < 3:
        raise ValueError(f"structure from motion needs at least 3 photos of the same object, {img_dir} has "
                         f"{len(names)}: {', '.join(names)}")
    width, height = _check_sizes(img_dir, names)
    pycolmap = _pycolmap()
    matcher, why = choose_matcher(names, opts)
    pairs = _pairs(names, matcher, opts.sequential_overlap)
    try:
        os.makedirs(workspace, exist_ok=True)
    except OSError as e:
        raise OSError(f"cannot write the camera poses to {workspace} ({e}): pass out_dir (a writable folder)") from None
    if not os.access(workspace, os.W_OK):
        raise PermissionError(f"cannot write the camera poses to {workspace}: the folder is read-only; pass out_dir "
                              "(a writable folder)")
    if progress:
        print(f"wtopo sfm: {len(names)} photos of {width}x{height} in {img_dir} -> {model_dir}\n"
              f"  matcher  {matcher}: {why}\n"
              f"  camera   {opts.camera_model}, one shared by all photos")
    db = os.path.join(workspace, "database.db")
    seconds = {}
    t0 = time.perf_counter()
    pycolmap.set_random_seed(opts.seed)
    with _quiet_colmap(pycolmap):
        focal_prior = _extract(pycolmap, db, img_dir, names, opts, progress)
        seconds["features"] = time.perf_counter() - t0
        if progress:
            print(f"  focal    prior {focal_prior}")
        t1 = time.perf_counter()
        _match(pycolmap, db, workspace, pairs, opts, progress)
        seconds["matching"] = time.perf_counter() - t1
        min_inliers = pycolmap.IncrementalPipelineOptions().min_num_matches
        keypoints, partners, best = _verified_partners(pycolmap, db, min_inliers)
        t2 = time.perf_counter()
        if not any(partners.values()):
            raise SfMError(f"no two of the {len(names)} photos in {img_dir} overlap: none of the {len(pairs)} matched "
                           f"pairs shares {min_inliers} geometrically verified feature matches (most: "
                           f"{max(best.values(), default=0)}). The photos must show the same surfaces from nearby "
                           "viewpoints, with texture (features per photo: "
                           f"{min(keypoints.values(), default=0)}-{max(keypoints.values(), default=0)})")
        rec, recs = _map(pycolmap, db, img_dir, workspace, len(names), opts, progress)
        seconds["mapping"] = time.perf_counter() - t2
    seconds["total"] = time.perf_counter() - t0
    seconds = {k: round(v, 3) for k, v in seconds.items()}
    registered = [] if rec is None else sorted(im.name for im in rec.images.values() if im.has_pose)
    others = {im.name: r.num_reg_images() for r in recs if r is not rec for im in r.images.values() if im.has_pose}
    dropped = _why_dropped(names, set(registered), others, keypoints, partners, best, min_inliers)
    need = max(opts.min_registered, math.ceil(opts.min_registered_fraction * len(names)))
    if len(registered) < need:
        partial = None
        if rec is not None:
            partial = os.path.join(workspace, "sparse", "partial")
            _write_model(rec, partial)
        kept = f"; the partial model ({len(registered)} images) is kept in {partial}" if partial else ""
        raise SfMError(f"only {len(registered)} of {len(names)} photos in {img_dir} were registered (at least {need} "
                       f"are needed: min_registered_fraction={opts.min_registered_fraction:g}, "
                       f"min_registered={opts.min_registered}){kept}. Dropped: {_names_list(dropped)}",
                       partial_model=partial, dropped=dropped)
    _write_model(rec, model_dir)
    res = SfMResult(model_dir, workspace, img_dir, list(names), registered, dropped, matcher, why,
                    _camera_dict(rec, focal_prior), int(rec.num_points3D()),
                    float(rec.compute_mean_reprojection_error()), seconds)
    with open(os.path.join(workspace, SFM_SUMMARY), "w") as fh:
        json.dump({k: v for k, v in res.to_dict().items() if k not in ("model_dir", "workspace", "image_dir",
                                                                         "reused")}, fh, indent=1)
    if progress:
        print(f"wtopo sfm: {len(registered)} of {len(names)} photos registered, {res.points} points, mean "
              f"reprojection error {res.reprojection_error:.2f} px, {seconds['total']:.1f} s")
        for name, why in list(dropped.items())[:_MAX_NAMED]:
            print(f"  dropped  {name}: {why}")
        if len(dropped) > _MAX_NAMED:
            print(f"  dropped  and {len(dropped) - _MAX_NAMED} more (sfm.json lists them)")
    return res


def load_photos(path, *, out_dir=None, options: SfMOptions | None = None, reuse: bool = True, progress: bool = True,
                undistort: bool = True, **kwargs):
    """A :class:`wtopo.Scene` from a folder of photographs: :func:`run_sfm`, then the COLMAP loader
    on its ``sparse/0`` (registered images only; the model's points seed the surfels).
    ``scene.info["sfm"]`` holds :meth:`SfMResult.to_dict`.

    Args:
        path: folder of photographs, or a folder holding ``images/``. Masks are read from a
            ``masks/`` folder beside the image folder (``masks/<name>`` or ``masks/<name>.png``);
            RGBA photos' alpha is the mask.
        out_dir: :func:`run_sfm`'s workspace (default beside the images).
        options: :class:`SfMOptions`.
        reuse: reuse an existing ``sparse/0``.
        progress: print the matcher choice and show progress bars.
        undistort: resample the photos (and masks) at their full size to pinhole cameras of the same
            intrinsics, as COLMAP's ``image_undistorter`` does before multi-view stereo, then
            downscale them. The fit renders distorted cameras exactly, but fits less well from them:
            on the 64-view synthetic capture at 64 px the recovered ``SIMPLE_RADIAL`` camera (k =
            0.013 where the truth has none) made the fit's Chamfer 15 % worse than the true
            cameras', the same cameras without the distortion 1 %.
        **kwargs: :func:`~wtopo.loaders.load_colmap` options (``background``, ``downscale``).

    Raises:
        The errors of :func:`run_sfm` and :func:`~wtopo.loaders.load_colmap`.
    """
    from .colmap import load_colmap

    res = run_sfm(path, out_dir=out_dir, options=options, reuse=reuse, progress=progress)
    if not undistort:
        scene = load_colmap(res.workspace, images_dir=res.image_dir, **kwargs)
    else:
        downscale = kwargs.pop("downscale", 1)
        scene = _undistorted(load_colmap(res.workspace, images_dir=res.image_dir, **kwargs), downscale)
    scene.info["sfm"] = res.to_dict()
    return scene


def _undistorted(scene, downscale: float):
    """``scene`` with pinhole cameras (same ``K``) and its images and masks resampled to them
    (bilinear; a pinhole pixel whose distorted position falls outside the photo takes the nearest
    border pixel: with pincushion distortion a thin rim, k = 0.013 at 256 px: under one pixel), then
    divided in size by ``downscale`` (area average, as the loaders do)."""
    import dataclasses

    import numpy as np
    import torch

    from ..camera import Camera
    from ._common import ImageStack

    cams = []
    imgs = torch.as_tensor(scene.images)
    masks = None if scene.masks is None else torch.as_tensor(scene.masks)
    out_i, out_m = [], []
    for i, cam in enumerate(scene.cameras):
        pin = Camera(cam.K, cam.world_to_camera, cam.width, cam.height, None, cam.name)
        img, m = imgs[i], None if masks is None else masks[i]
        if cam.distortion is not None:
            u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)  # pixel centres
            K = cam.K
            y = (v - K[1, 2]) / K[1, 1]
            x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
            xd = cam.distort(np.stack([x, y], axis=-1))
            ud = K[0, 0] * xd[..., 0] + K[0, 1] * xd[..., 1] + K[0, 2]
            vd = K[1, 1] * xd[..., 1] + K[1, 2]
            # grid_sample's normalised coordinates with align_corners=False: -1 and 1 are the outer pixel edges
            grid = torch.as_tensor(np.stack([2 * ud / cam.width - 1, 2 * vd / cam.height - 1], axis=-1),
                                   dtype=torch.float32)[None]
            img = torch.nn.functional.grid_sample(img.permute(2, 0, 1)[None].float(), grid, mode="bilinear",
                                                  padding_mode="border", align_corners=False)[0].permute(1, 2, 0)
            if m is not None:
                m = torch.nn.functional.grid_sample(m[None, None].float(), grid, mode="bilinear",
                                                    padding_mode="border", align_corners=False)[0, 0] >= 0.5
        out_i.append(img.numpy())
        out_m.append(None if m is None else m.numpy())
        cams.append(pin)
    stack = ImageStack(downscale, None, source="the undistorted photos")
    for cam, img, m in zip(cams, out_i, out_m):
        stack.add(cam, img, m)
    cams, images, masks = stack.arrays()
    return dataclasses.replace(scene, cameras=cams, images=images, masks=masks)
