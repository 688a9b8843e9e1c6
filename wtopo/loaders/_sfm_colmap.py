# SPDX-License-Identifier: Apache-2.0
"""The pycolmap steps of :func:`wtopo.loaders.sfm.run_sfm`: feature extraction, matching,
incremental mapping with a last robust bundle adjustment, why images were dropped, and the model's
files (pycolmap is imported lazily: an optional dependency)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile

from ._sfm_options import _MAX_NAMED, SfMOptions

SFM_INSTALL_HINT = 'pip install "wtopo[sfm]"  (or: pip install pycolmap)'


_MATCH_CHUNK = 64  # image pairs per matching call: one progress-bar step (a call costs ~1 ms of set-up)
_EXTRACT_CHUNK = 4  # images per feature-extraction call: one progress-bar step


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
