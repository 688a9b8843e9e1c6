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
"""

from __future__ import annotations

import contextlib
import enum
import itertools
import json
import math
import os
import re
import shutil
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field

__all__ = ["IMAGE_EXTENSIONS", "Matcher", "SfMOptions", "SfMResult", "SfMError", "run_sfm", "load_photos",
           "find_photos", "choose_matcher"]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
"""File suffixes (any case) read as photographs: the formats COLMAP's image reader decodes."""

SFM_INSTALL_HINT = 'pip install "wtopo[sfm]"  (or: pip install pycolmap)'

_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")  # what load_colmap reads
_MATCH_CHUNK = 64  # image pairs per matching call: one progress-bar step (a call costs ~1 ms of set-up)
_EXTRACT_CHUNK = 4  # images per feature-extraction call: one progress-bar step
_MAX_NAMED = 20  # an error names at most this many dropped images (then "and N more")
SFM_SUMMARY = "sfm.json"
"""What :func:`run_sfm` did, written in its workspace beside ``sparse/`` (also how a later load tells its model)."""
_IMAGE_FOLDERS = ("images", "image")  # a workspace's image folder: the model goes beside it, not into it


class Matcher(str, enum.Enum):
    """Which image pairs are matched."""

    EXHAUSTIVE = "exhaustive"
    """Every pair: N (N - 1) / 2 pairs. Robust for any capture order; quadratic in N."""
    SEQUENTIAL = "sequential"
    """Each image with its ``sequential_overlap`` successors in name order and those 2, 4, 8, ...
    further on (COLMAP's quadratic overlap): video frames, linear in N."""


class SfMError(ValueError):
    """Structure from motion ran but did not give a usable model (too few images registered, no
    overlap between the images). ``partial_model`` is the folder the largest partial model was
    written to, or ``None``; ``dropped`` maps each unregistered image to the reason."""

    def __init__(self, message: str, *, partial_model: str | None = None, dropped: dict | None = None):
        super().__init__(message)
        self.partial_model = partial_model
        self.dropped = dict(dropped or {})


@dataclass(kw_only=True)
class SfMOptions:
    """Settings of :func:`run_sfm`."""

    matcher: str | None = None
    """``"exhaustive"``, ``"sequential"`` or ``None`` to choose by the image count
    (:func:`choose_matcher`)."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model shared by all images: ``SIMPLE_RADIAL`` (f, cx, cy, k; phones and most
    cameras) or ``OPENCV`` (fx, fy, cx, cy, k1, k2, p1, p2); ``SIMPLE_PINHOLE``, ``PINHOLE`` and
    ``RADIAL`` also work."""
    exhaustive_max_images: int = 300
    """Up to this many images every pair is matched (300 images: 44,850 pairs, about an hour on 2
    cores at 8k features); beyond it the sequential matcher is chosen."""
    sequential_overlap: int = 10
    """Successors each image is matched with by the sequential matcher."""
    max_image_size: int = 2000
    """Longest side, pixels, features are extracted at (larger photos are downsampled for SIFT only)."""
    max_num_features: int = 8192
    """SIFT features kept per image."""
    min_registered_fraction: float = 0.5
    """The run fails (:class:`SfMError`) when fewer than this fraction of the images get a pose."""
    min_registered: int = 3
    """... or fewer than this many."""
    num_threads: int = -1
    """CPU threads for extraction, matching and mapping (-1: all cores)."""
    seed: int = 0
    """Random seed of RANSAC and the mapper."""
    robust_refinement: float = 1.0
    """Scale (pixels) of the Cauchy loss of a last global bundle adjustment of the model; 0: none.
    COLMAP's own adjustments minimise squared errors, which a few wrong matches (repetitive texture:
    bricks, gravel) bias: on the 64-view synthetic capture of ``tests/test_sfm.py`` this pass took
    the camera-centre error from 0.32 % to 0.11 % of the camera extent and the focal length from
    0.6 % to 0.3 % off, at the same mean reprojection error (``benchmarks/sfm.md``)."""

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field and its value."""
        if self.matcher is not None and self.matcher not in [m.value for m in Matcher]:
            raise ValueError(f"matcher must be 'exhaustive', 'sequential' or None, got {self.matcher!r}")
        if self.camera_model not in _CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {', '.join(_CAMERA_MODELS)}, got {self.camera_model!r}")
        for name, lo in (("exhaustive_max_images", 2), ("sequential_overlap", 1), ("max_image_size", 16),
                         ("max_num_features", 16), ("min_registered", 2)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        f = self.min_registered_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f <= 1:
            raise ValueError(f"min_registered_fraction must be a number in [0, 1], got {f!r}")
        r = self.robust_refinement
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not (math.isfinite(r) and r >= 0):
            raise ValueError(f"robust_refinement must be a finite number >= 0 (pixels), got {r!r}")
        if isinstance(self.num_threads, bool) or not isinstance(self.num_threads, int) or self.num_threads == 0 \
                or self.num_threads < -1:
            raise ValueError(f"num_threads must be -1 (all cores) or an integer >= 1, got {self.num_threads!r}")


@dataclass
class SfMResult:
    """What :func:`run_sfm` did (also written to ``workspace/sfm.json``)."""

    model_dir: str
    """The model folder, ``workspace/sparse/0``."""
    workspace: str
    """The folder holding ``database.db``, ``sparse/`` and ``sfm.json``."""
    image_dir: str
    """The folder of the photographs."""
    images: list
    """Every image name, sorted."""
    registered: list
    """Names of the images that got a pose."""
    dropped: dict
    """Unregistered image name -> why."""
    matcher: str
    matcher_reason: str
    camera: dict
    """The shared camera: ``{"model", "width", "height", "params", "focal_prior"}``."""
    points: int
    """3D points of the model (they seed the surfels)."""
    reprojection_error: float | None
    """Mean reprojection error of the model, pixels."""
    seconds: dict = field(default_factory=dict)
    """Wall time of each step (``features``, ``matching``, ``mapping``, ``total``)."""
    reused: bool = False
    """The model was already there; nothing ran."""

    def to_dict(self) -> dict:
        """JSON-ready fields."""
        return asdict(self)


# -- finding the photographs -------------------------------------------------------------------------


def _image_names(folder: str) -> list[str]:
    try:
        entries = sorted(os.listdir(folder))
    except OSError:
        return []
    return [e for e in entries if e.lower().endswith(IMAGE_EXTENSIONS) and os.path.isfile(os.path.join(folder, e))]


def find_photos(path: str) -> tuple[str, list[str]] | None:
    """``(image folder, sorted image names)`` when ``path`` is a folder of photographs (or holds
    one called ``images``, or ``image`` as in the IDR / NeuS layout), else ``None``. Only files with
    an :data:`IMAGE_EXTENSIONS` suffix count; other files (a ``masks/`` folder, notes) are ignored."""
    p = os.fspath(path)
    for d in (*(os.path.join(p, f) for f in _IMAGE_FOLDERS), p):
        names = _image_names(d)
        if names:
            return d, names
    return None


def _workspace(image_dir: str) -> str:
    named = os.path.basename(os.path.normpath(image_dir)) in _IMAGE_FOLDERS
    return os.path.dirname(os.path.normpath(image_dir)) if named else image_dir


def _frame_sequence(names: list[str]) -> bool:
    """Whether the names read as numbered frames of one sequence (``frame_0001.jpg``, ...)."""
    parts = [re.fullmatch(r"(.*?)(\d+)(\.[^.]+)", n) for n in names]
    if not all(parts) or len({(m.group(1), m.group(3)) for m in parts}) != 1:
        return False
    nums = sorted(int(m.group(2)) for m in parts)
    steps = {b - a for a, b in zip(nums, nums[1:])}
    return len(steps) == 1 and steps != {0}


def choose_matcher(names: list[str], options: SfMOptions) -> tuple[str, str]:
    """``(matcher, reason)``: the configured matcher, or exhaustive up to
    :attr:`SfMOptions.exhaustive_max_images` images and sequential beyond (video frames)."""
    n = len(names)
    pairs = n * (n - 1) // 2
    if options.matcher is not None:
        return options.matcher, f"set in the options ({n} images)"
    if n <= options.exhaustive_max_images:
        return Matcher.EXHAUSTIVE.value, (f"{n} images <= {options.exhaustive_max_images}: all {pairs} pairs are "
                                          "matched (robust to any capture order)")
    why = (f"{n} images > {options.exhaustive_max_images}: matching all {pairs} pairs would take hours; each image "
           f"is matched with its {options.sequential_overlap} successors in name order")
    if _frame_sequence(names):
        return Matcher.SEQUENTIAL.value, why + " (the names number the frames of one sequence: a video)"
    return Matcher.SEQUENTIAL.value, why + (" (the names do not number one sequence: if the photos are not in capture "
                                            "order, pass matcher='exhaustive')")


def _pairs(names: list[str], matcher: str, overlap: int) -> list[tuple[str, str]]:
    if matcher == Matcher.EXHAUSTIVE.value:
        return list(itertools.combinations(names, 2))
    n = len(names)
    steps = sorted(set(range(1, overlap + 1)) | {2 ** k for k in range(overlap)})  # COLMAP's quadratic overlap
    return [(names[i], names[i + s]) for i in range(n) for s in steps if i + s < n]


def _check_sizes(image_dir: str, names: list[str]) -> tuple[int, int]:
    """The one ``(width, height)`` of all images (headers only); ``ValueError`` listing the sizes if not one."""
    from PIL import Image

    sizes: dict[tuple[int, int], list[str]] = {}
    for n in names:
        p = os.path.join(image_dir, n)
        try:
            with Image.open(p) as im:
                sizes.setdefault(im.size, []).append(n)
        except (OSError, SyntaxError, ValueError) as e:
            raise ValueError(f"cannot read image {p}: {e}") from None
    if len(sizes) > 1:
        listed = "; ".join(f"{w}x{h}: {len(v)} image(s), e.g. {v[0]}" for (w, h), v in
                           sorted(sizes.items(), key=lambda kv: -len(kv[1])))
        raise ValueError(f"the photos in {image_dir} must share one size, since one camera is fitted to all of them; "
                         f"got {len(sizes)} sizes (WxH): {listed}. Resize or crop them to one size (rotated portrait "
                         "shots: rotate them to the landscape ones)")
    return next(iter(sizes))


# -- running pycolmap --------------------------------------------------------------------------------


def _pycolmap():
    try:
        import pycolmap
    except ImportError as e:
        raise ModuleNotFoundError(f"camera poses from photographs need pycolmap, which is not installed ({e}); "
                                  f"install it with: {SFM_INSTALL_HINT}", name="pycolmap") from None
    return pycolmap


@contextlib.contextmanager
def _quiet_colmap(pycolmap):
    """COLMAP's own log (glog, every step at INFO) down to errors while the progress bars run."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _bar(progress: bool, total: int, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not progress, dynamic_ncols=True, leave=True)


def _extract(pycolmap, db: str, image_dir: str, names: list[str], opts: SfMOptions, progress: bool) -> str:
    """Import the images with one shared camera and extract SIFT features; the focal prior's source."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    database = pycolmap.Database.open(db)  # creates the file; import_images needs it to exist
    try:
        known = {im.name for im in database.read_all_images()}
    finally:
        database.close()
    new = [n for n in names if n not in known]
    if new:
        if known:  # the shared camera exists: new images join it
            database = pycolmap.Database.open(db)
            try:
                reader.existing_camera_id = database.read_all_cameras()[0].camera_id
            finally:
                database.close()
        pycolmap.import_images(db, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=new, options=reader)
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = opts.num_threads
    ext.max_image_size = opts.max_image_size
    ext.sift.max_num_features = opts.max_num_features
    with _bar(progress, len(names), "sfm features") as bar:
        for k in range(0, len(names), _EXTRACT_CHUNK):  # images that have features already are skipped
            chunk = names[k:k + _EXTRACT_CHUNK]
            pycolmap.extract_features(db, image_dir, image_names=chunk, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
            bar.update(len(chunk))
    database = pycolmap.Database.open(db)
    try:
        cam = database.read_all_cameras()[0]
    finally:
        database.close()
    if cam.has_prior_focal_length:
        return f"EXIF ({cam.mean_focal_length():.1f} px)"
    return f"none in the EXIF data: {reader.default_focal_length_factor:g} x the longest side " \
           f"({cam.mean_focal_length():.1f} px)"


def _match(pycolmap, db: str, workspace: str, pairs: list, opts: SfMOptions, progress: bool) -> None:
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = opts.num_threads
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = opts.seed
    with tempfile.TemporaryDirectory(dir=workspace, prefix=".wtopo_pairs_") as tmp, \
            _bar(progress, len(pairs), "sfm matching") as bar:
        listing = os.path.join(tmp, "pairs.txt")
        for k in range(0, len(pairs), _MATCH_CHUNK):  # pairs matched before are skipped
            chunk = pairs[k:k + _MATCH_CHUNK]
            with open(listing, "w") as fh:
                fh.writelines(f"{a} {b}\n" for a, b in chunk)
            po = pycolmap.ImportedPairingOptions()
            po.match_list_path = listing
            pycolmap.match_image_pairs(db, matching_options=mo, pairing_options=po, verification_options=verify,
                                       device=pycolmap.Device.cpu)
            bar.update(len(chunk))


def _map(pycolmap, db: str, image_dir: str, workspace: str, n_images: int, opts: SfMOptions, progress: bool):
    po = pycolmap.IncrementalPipelineOptions()
    po.num_threads = opts.num_threads
    po.random_seed = opts.seed
    po.min_model_size = opts.min_registered  # COLMAP's default (10) would discard small image sets
    with tempfile.TemporaryDirectory(dir=workspace, prefix=".wtopo_mapping_") as tmp, \
            _bar(progress, n_images, "sfm mapping") as bar:
        # the mapper calls this after each image it registers (the first pair counts as one call)
        recs = pycolmap.incremental_mapping(db, image_dir, tmp, options=po, next_image_callback=lambda: bar.update(1))
        best = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
        if best is not None:
            bar.n = best.num_reg_images()
            bar.refresh()
    if best is not None and opts.robust_refinement > 0:
        _refine(pycolmap, best, opts.robust_refinement, opts.num_threads)
    return best, list(recs.values())


_REFINE_ITERATIONS = 300  # Levenberg-Marquardt steps of the last adjustment (Ceres' 100 stopped short on 64 views)


def _refine(pycolmap, rec, loss_scale: float, threads: int) -> None:
    """Global bundle adjustment of ``rec`` in place with a Cauchy loss of ``loss_scale`` pixels.

    Built from the adjuster rather than ``pycolmap.bundle_adjustment``, which logs its heading to
    stderr whatever the log level."""
    ba = pycolmap.BundleAdjustmentOptions()
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = float(loss_scale)
    ba.ceres.solver_options.num_threads = threads
    ba.ceres.solver_options.max_num_iterations = _REFINE_ITERATIONS
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()
    rec.update_point_3d_errors()


def _verified_partners(pycolmap, db: str, min_inliers: int) -> tuple[dict, dict, dict]:
    """Per image name: keypoint count, number of images it shares >= ``min_inliers`` verified matches
    with, and its largest inlier count."""
    database = pycolmap.Database.open(db)
    try:
        by_id = {im.image_id: im.name for im in database.read_all_images()}
        keypoints = {name: database.num_keypoints_for_image(i) for i, name in by_id.items()}
        pair_ids, inliers = database.read_two_view_geometry_num_inliers()
    finally:
        database.close()
    partners = dict.fromkeys(by_id.values(), 0)
    best = dict.fromkeys(by_id.values(), 0)
    for pid, m in zip(pair_ids, inliers):
        for iid in pycolmap.pair_id_to_image_pair(pid):
            name = by_id[iid]
            best[name] = max(best[name], int(m))
            if m >= min_inliers:
                partners[name] += 1
    return keypoints, partners, best


def _why_dropped(names, registered, others, keypoints, partners, best, min_inliers) -> dict:
    out = {}
    for n in names:
        if n in registered:
            continue
        if keypoints.get(n, 0) < min_inliers:
            out[n] = f"{keypoints.get(n, 0)} features (textureless or blurred)"
        elif partners.get(n, 0) == 0:
            out[n] = (f"no other image shares {min_inliers} geometrically verified matches with it (best "
                      f"{best.get(n, 0)}): it does not overlap the others")
        elif n in others:
            out[n] = f"registered only in a separate model of {others[n]} images that shares none with the main one"
        else:
            out[n] = (f"overlaps {partners[n]} image(s) (up to {best[n]} verified matches) but its pose could not be "
                      "estimated from the model's points")
    return out


def _names_list(dropped: dict) -> str:
    items = [f"{n} ({why})" for n, why in list(dropped.items())[:_MAX_NAMED]]
    more = len(dropped) - _MAX_NAMED
    return "; ".join(items) + (f"; and {more} more" if more > 0 else "")


def _write_model(rec, folder: str) -> None:
    if os.path.isdir(folder):
        shutil.rmtree(folder)
    os.makedirs(folder)
    rec.write_binary(folder)
    rec.write_text(folder)


def _camera_dict(rec, focal_prior: str) -> dict:
    cam = next(iter(rec.cameras.values()))
    return {"model": cam.model_name, "width": int(cam.width), "height": int(cam.height),
            "params": [float(v) for v in cam.params], "focal_prior": focal_prior}


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
            cameras', the same cameras without the distortion 1 % (``benchmarks/sfm.md``).
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
