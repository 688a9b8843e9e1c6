# SPDX-License-Identifier: Apache-2.0
"""Camera poses for a folder of photos (wtopo.loaders.sfm, pycolmap): a synthetic textured capture
rendered by ``wtopo.scenes.from_mesh`` with known cameras, its failure modes, reuse, and the CLI.

pycolmap is a test dependency (``pip install -e ".[test]"`` pulls ``wtopo[sfm]``): these tests
import it and fail, never skip, when it is missing.
"""

import json
import os
import sys

import numpy as np
import pycolmap  # noqa: F401  (a missing test dependency fails here, loudly)
import pytest
import torch
from fit_configs import small_fit_config
from PIL import Image

from wtopo import Scene, cli, load_scene, ops, scenes
from wtopo.fitting import fit
from wtopo.fitting.evaluate import geometry_metrics
from wtopo.loaders import SfMError, SfMOptions, detect_format, load_photos, run_sfm
from wtopo.loaders.sfm import choose_matcher
from wtopo.metrics import align_similarity

# The capture: the bunny (astronaut albedo) in the textured room (gravel floor, brick walls) from
# the upper hemisphere. Measured on the 2-core CPU (seed 0): 64 views of 256 px registered 64 of 64
# with camera centres 0.32 % of the camera extent from the truth (48 views: 43 of 48, 0.36-0.45 %;
# 256 px images give SIFT ~500-1,000 features each, the sparse room texture bounds the accuracy).
N_VIEWS = 64
RES = 256
CENTRE_RMS = 0.01  # issue 17: recovered camera centres within 1 % of the camera extent (RMS)
MIN_REGISTERED = 0.9  # of the views; 64 of 64 were measured
# The fits: test-sized (150 + 50 iterations) on 32 px images of every other registered view (32
# views), two seeds each, means compared. Measured in the true frame (below), Chamfer % of the
# diagonal, true / recovered: 32 px, seeds 0, 1: 1.115 / 1.037, 0.988 / 0.994 (ratio of means 0.97);
# 64 px (lab/sfm.md, 4 x 60-190 s of fits: too slow here), seeds 0, 1: 0.752, 0.813 / 0.871,
# 0.925 (ratio 1.15, camera alignment only), 1.07 after the Tanks-and-Temples ICP refinement
# (metrics.refine_alignment), and 0.95 with the recovered poses but the true intrinsics: at 64 px
# the recovered intrinsics (focal 0.35 % long, k = 0.013) make the gap, not the poses.
FIT_DOWNSCALE = 8
FIT_EVERY = 2
FIT_SEEDS = (0, 1)  # one fit's Chamfer moves by 5-10 % with its random draws at this size
CHAMFER_RATIO = 1.10  # issue 17: the fit from recovered cameras within 10 % of the fit from the true ones


def _save_rgba(path, rgb, mask):
    a = np.concatenate([np.clip(rgb, 0, 1), mask[..., None].astype(np.float32)], axis=-1)
    Image.fromarray((a * 255 + 0.5).astype(np.uint8)).save(path)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Photos only: ``root/images/000.png ...`` (RGBA, alpha = the bunny's silhouette, so the fit
    is an object fit; COLMAP ignores alpha and sees the whole room) and the rendered scene."""
    scene = scenes.load("bunny_room", n_views=N_VIEWS, resolution=RES)
    gt = scene.gt_mesh  # the bunny alone: its silhouette is the mask (nothing of the room is in front of it)
    masks = ops.raycast_mesh(torch.as_tensor(gt.vertices, dtype=torch.float32),
                             torch.as_tensor(gt.faces, dtype=torch.int32), scene.cameras).mask.numpy()
    root = tmp_path_factory.mktemp("capture")
    os.makedirs(root / "images")
    for i, (rgb, m) in enumerate(zip(np.asarray(scene.images), masks)):
        _save_rgba(root / "images" / f"{i:03d}.png", rgb, m)
    return root, scene


@pytest.fixture(scope="module")
def recovered(capture):
    """The structure-from-motion run on the capture (the folder holds images only)."""
    root, _ = capture
    assert detect_format(root) == "photos"
    return run_sfm(root, progress=False)


def _true_centres(scene, names):
    return np.array([scene.cameras[int(n.split(".")[0])].center for n in names])


def test_recovered_camera_centres_match_the_true_ones(capture, recovered):
    """Recover the camera centres of 64 rendered views within 1 % RMS of the camera extent after a similarity."""
    root, scene = capture
    r = recovered
    assert len(r.registered) >= MIN_REGISTERED * N_VIEWS, r.dropped
    assert r.matcher == "exhaustive" and "64 images" in r.matcher_reason
    assert r.camera["model"] == "SIMPLE_RADIAL" and (r.camera["width"], r.camera["height"]) == (RES, RES)
    assert 0 < r.reprojection_error < 1.0  # pixels
    for stem in ("cameras", "images", "points3D"):
        for ext in ("bin", "txt"):
            assert os.path.isfile(os.path.join(r.model_dir, f"{stem}.{ext}"))
    assert r.model_dir == os.path.join(root, "sparse", "0")
    with open(root / "sfm.json") as fh:
        assert json.load(fh)["registered"] == r.registered
    loaded = load_scene(root)  # the model beside the images, reused
    names = [c.name for c in loaded.cameras]
    assert names == r.registered
    assert loaded.points is not None and len(loaded.points) == r.points >= 100  # they seed the surfels
    al = align_similarity(np.array([c.center for c in loaded.cameras]), _true_centres(scene, names))
    everything = np.array([c.center for c in scene.cameras])
    extent = float(np.linalg.norm(everything.max(0) - everything.min(0)))
    assert al.rms <= CENTRE_RMS * extent, f"camera centre RMS {al.rms / extent:.3%} of the extent"
    # the focal length too: the rendering's is known
    np.testing.assert_allclose(loaded.cameras[0].K[0, 0], scene.cameras[0].K[0, 0], rtol=0.02)


@pytest.mark.slow
def test_fit_from_recovered_cameras_matches_the_fit_from_true_ones(capture, recovered):
    """Fit from the recovered cameras to within 10 % of the Chamfer reached from the true cameras."""
    root, scene = capture
    sfm_scene = load_photos(root, downscale=FIT_DOWNSCALE, progress=False)  # reuses the model
    assert sfm_scene.masks is not None and sfm_scene.info["sfm"]["reused"]
    names = [c.name for c in sfm_scene.cameras]
    al = align_similarity(np.array([c.center for c in sfm_scene.cameras]), _true_centres(scene, names))
    # A controlled comparison: the same images, masks and seed points, and the recovered cameras moved
    # into the true frame by the centres' similarity, so both fits normalise alike and start from the
    # same random numbers; only the cameras differ. (Fits in different frames differ by 5-10 % in
    # Chamfer from their random draws alone at this size, as much as the margin.)
    every = slice(None, None, FIT_EVERY)
    kept = dict(images=sfm_scene.images[every], masks=sfm_scene.masks[every], points=al.apply(sfm_scene.points),
                point_colors=sfm_scene.point_colors)
    true_cams = [scene.cameras[int(n.split(".")[0])].scaled(1 / FIT_DOWNSCALE) for n in names]
    chamfer = {}
    for label, cams in (("true", true_cams), ("recovered", [al.apply_to_camera(c) for c in sfm_scene.cameras])):
        for seed in FIT_SEEDS:
            cfg = small_fit_config(150, 50, points=600, grids=(48, 64, 32), max_faces=1500, density_every=10,
                                   eval_every=0)
            cfg.runtime.seed = seed
            mesh = fit(Scene(cams[every], **kept), cfg, progress=False).mesh
            chamfer[label, seed] = geometry_metrics(mesh, scene.gt_mesh)["chamfer_rel"]
    true, rec = (np.mean([chamfer[label, s] for s in FIT_SEEDS]) for label in ("true", "recovered"))
    assert true < 0.03, chamfer  # the fit itself works (measured 1.0-1.1 %)
    assert rec <= CHAMFER_RATIO * true, chamfer


def test_second_run_reuses_the_model(capture, recovered, monkeypatch, capsys):
    """Reuse sparse/0 on a second run, through run_sfm and through the CLI's loader, without pycolmap."""
    root, _ = capture
    import wtopo.loaders.sfm as sfm

    def no_pycolmap():
        raise AssertionError("pycolmap was called although sparse/0 exists")

    monkeypatch.setattr(sfm, "_pycolmap", no_pycolmap)
    again = run_sfm(root)
    assert again.reused and again.registered == recovered.registered and again.matcher == recovered.matcher
    assert "reusing" in capsys.readouterr().out
    scene = cli._load(str(root), sfm=True, progress=False)
    assert [c.name for c in scene.cameras] == recovered.registered
    assert all(c.distortion is None for c in scene.cameras)  # undistorted as on the first run
    assert detect_format(root) == "photos"  # the model run_sfm wrote (sfm.json beside sparse/)
    os.remove(root / "sfm.json")
    try:
        assert detect_format(root) == "colmap"  # a model made elsewhere is a COLMAP dataset
    finally:
        with open(root / "sfm.json", "w") as fh:
            json.dump(recovered.to_dict(), fh)


def _noise_photos(folder, n, size=(160, 120), seed=0, ext="png"):
    os.makedirs(folder, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(
            os.path.join(folder, f"noise_{i:02d}.{ext}"))


def test_no_overlap_is_a_clear_error(tmp_path):
    """Fail on photos that share nothing (random noise), saying so and how many pairs were tried."""
    _noise_photos(tmp_path / "photos", 5)
    with pytest.raises(SfMError, match=r"no two of the 5 photos .* overlap: none of the 10 matched pairs"):
        run_sfm(tmp_path / "photos", progress=False)


def test_too_few_registered_names_the_dropped_images_and_keeps_the_partial_model(capture, tmp_path):
    """Fail when too few photos register: say how many, name the dropped ones and why, keep the partial model."""
    root, _ = capture
    photos = tmp_path / "photos"
    os.makedirs(photos)
    for i in range(0, N_VIEWS, 4):  # 16 views around the hemisphere
        os.symlink(root / "images" / f"{i:03d}.png", photos / f"{i:03d}.png")
    _noise_photos(photos, 4, size=(RES, RES))
    with pytest.raises(SfMError) as err:
        run_sfm(photos, out_dir=tmp_path / "ws", options=SfMOptions(min_registered_fraction=0.9), progress=False)
    msg, e = str(err.value), err.value
    assert "of 20 photos" in msg and "at least 18 are needed" in msg
    assert set(e.dropped) >= {f"noise_{i:02d}.png" for i in range(4)}
    assert "noise_00.png (no other image shares" in msg
    assert e.partial_model == str(tmp_path / "ws" / "sparse" / "partial") and e.partial_model in msg
    assert os.path.isfile(os.path.join(e.partial_model, "images.bin"))
    assert not os.path.exists(tmp_path / "ws" / "sparse" / "0")  # a later run does not take it for a result
    assert not os.path.exists(photos / "sparse")  # out_dir: nothing written beside the photos


def test_mixed_image_sizes_and_too_few_images_are_errors(tmp_path):
    """Refuse photos of several sizes (listing them) and fewer than 3 photos, before any work."""
    _noise_photos(tmp_path / "mixed", 2, size=(64, 48))
    _noise_photos(tmp_path / "mixed", 1, size=(48, 64), seed=1, ext="jpg")
    with pytest.raises(ValueError, match=r"share one size.*64x48: 2 image\(s\), e.g. noise_00.png; 48x64: 1 image"):
        run_sfm(tmp_path / "mixed", progress=False)
    _noise_photos(tmp_path / "two", 2)
    with pytest.raises(ValueError, match="at least 3 photos.* has 2"):
        run_sfm(tmp_path / "two", progress=False)
    os.makedirs(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="holds no photographs"):
        run_sfm(tmp_path / "empty", progress=False)


def test_focal_prior_from_exif(capture, tmp_path):
    """Take the focal length prior from the photos' EXIF data (35 mm equivalent) when they carry it."""
    root, scene = capture
    f_px = scene.cameras[0].K[0, 0]
    # COLMAP reads FocalLengthIn35mmFilm against the 43.27 mm diagonal of a 35 mm frame
    f35 = int(round(f_px * 43.2666 / np.hypot(RES, RES)))
    photos = tmp_path / "jpg"
    os.makedirs(photos)
    for i in range(0, N_VIEWS, 2):  # 32 views (sparser subsets register only half: 16 views, 8 of 16)
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = f35  # Exif IFD, FocalLengthIn35mmFilm
        Image.open(root / "images" / f"{i:03d}.png").convert("RGB").save(photos / f"{i:03d}.jpg", exif=exif,
                                                                          quality=95)
    r = run_sfm(photos, progress=False)
    assert r.camera["focal_prior"].startswith("EXIF"), r.camera
    np.testing.assert_allclose(r.camera["params"][0], f_px, rtol=0.03)


def test_missing_pycolmap_is_one_cli_line_saying_what_to_install(tmp_path, monkeypatch, capsys):
    """Say 'pip install "wtopo[sfm]"' in one 'wtopo fit: error:' line, exit 2, when pycolmap is missing."""
    _noise_photos(tmp_path / "photos", 3)
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # import pycolmap now raises ImportError
    assert cli.main(["fit", str(tmp_path / "photos"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("wtopo fit: error: ") and err.count("\n") == 1
    assert 'pip install "wtopo[sfm]"' in err
    assert cli.main(["fit", "bunny", "--sfm", "--out", str(tmp_path / "run")]) == 2
    assert "--sfm takes a folder of photographs" in capsys.readouterr().err


def test_matcher_choice_and_options():
    """Match every pair up to exhaustive_max_images, successors beyond (saying why), and check options."""
    opts = SfMOptions()
    m, why = choose_matcher([f"{i}.jpg" for i in range(48)], opts)
    assert m == "exhaustive" and "1128 pairs" in why
    m, why = choose_matcher([f"frame_{i:05d}.jpg" for i in range(400)], opts)
    assert m == "sequential" and "video" in why and "10 successors" in why
    m, why = choose_matcher([f"IMG_{i * 7 % 401:04d}.jpg" for i in range(400)], opts)
    assert m == "sequential" and "matcher='exhaustive'" in why
    assert choose_matcher(["a.jpg", "b.jpg"], SfMOptions(matcher="sequential"))[0] == "sequential"
    for bad, field in ((dict(camera_model="FISHEYE"), "camera_model"), (dict(matcher="vocab"), "matcher"),
                       (dict(min_registered_fraction=1.5), "min_registered_fraction"),
                       (dict(num_threads=0), "num_threads"), (dict(sequential_overlap=0), "sequential_overlap")):
        with pytest.raises(ValueError, match=field):
            run_sfm(".", options=SfMOptions(**bad), progress=False)


def test_align_similarity_recovers_a_known_similarity():
    """Recover scale, rotation and translation exactly; refuse colinear points."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(12, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))  # a proper rotation
    y = 3.5 * x @ rot.T + [1.0, -2.0, 0.5]
    al = align_similarity(x, y)
    np.testing.assert_allclose(al.scale, 3.5, rtol=1e-12)
    np.testing.assert_allclose(al.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(al.apply(x), y, atol=1e-12)
    assert al.rms < 1e-12
    mirrored = y * [1, 1, -1]  # no rotation maps x onto a mirror image: the best one leaves residuals
    assert np.linalg.det(align_similarity(x, mirrored).rotation) == pytest.approx(1.0)
    cam = scenes.rig_cameras("sphere", 1, [0, 0, 0], 1.0, resolution=(32, 24))[0]
    moved = align_similarity(y, x).apply_to_camera(cam)  # the same camera in x's frame
    np.testing.assert_allclose(moved.project(x)[0], cam.project(y)[0], atol=1e-9)
    with pytest.raises(ValueError, match="one line"):
        align_similarity(np.outer(np.arange(5.0), [1, 2, 3]), y[:5])


# refine_alignment: a similarity of a camera alignment's size (scale 1 %, 1 degree, 0.5 % shift)
# undone: measured scale within 2e-5 and vertices within 0.006 % of the diagonal (20k samples); the
# tolerances leave 10-50x for other platforms' round-off
REFINE_SCALE_TOL = 1e-3
REFINE_VERTEX_TOL = 1e-3  # of the diagonal


def test_refine_alignment_undoes_a_small_similarity():
    """Recover a small similarity between two copies of the bunny by ICP (Tanks and Temples' refinement)."""
    from wtopo.metrics import SimilarityAlignment, refine_alignment

    bunny, _ = scenes.bunny_mesh()
    v = np.asarray(bunny.vertices, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    a = np.radians(1.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    moved = SimilarityAlignment(1.01, rot, 0.005 * diag * np.array([1.0, -0.5, 0.3]), np.zeros(1))
    source = moved.apply_to_mesh(bunny)  # the bunny displaced; refining maps it back onto the bunny
    al = refine_alignment(source, bunny)
    np.testing.assert_allclose(al.scale * moved.scale, 1.0, atol=REFINE_SCALE_TOL)
    back = al.apply(moved.apply(v))
    assert np.abs(back - v).max() < REFINE_VERTEX_TOL * diag, np.abs(back - v).max() / diag
    assert np.median(al.residuals) < REFINE_VERTEX_TOL * diag
    again = refine_alignment(source, bunny, initial=al, iterations=1)  # starting at the answer stays there
    np.testing.assert_allclose(again.apply(source.vertices), al.apply(source.vertices), atol=REFINE_VERTEX_TOL * diag)
    with pytest.raises(ValueError, match="iterations"):
        refine_alignment(source, bunny, iterations=0)
    far = SimilarityAlignment(1.0, np.eye(3), np.array([diag, 0, 0]), np.zeros(1)).apply_to_mesh(bunny)
    with pytest.raises(ValueError, match="no point of source lies within"):
        refine_alignment(far, bunny)


UNDISTORT_TOL = 0.01  # bilinear resampling of a smooth pattern (period 20 px, amplitude 0.25): measured 0.005


def test_undistorted_photos_become_pinhole_views():
    """Resample a photo taken through radial distortion to the pinhole camera of the same K, mask too."""
    from wtopo import Camera
    from wtopo.loaders.sfm import _undistorted

    w = h = 64
    K = np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]])
    cam = Camera(K, np.eye(4), w, h, np.array([0.05, 0, 0, 0, 0]), "a.png")

    def pattern(u, v):  # the pinhole view: smooth, so bilinear resampling is nearly exact
        return 0.5 + 0.25 * np.sin(2 * np.pi * u / 20) * np.cos(2 * np.pi * v / 20)

    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = cam.undistort(np.stack([(u - 32) / 80, (v - 32) / 80], axis=-1))  # where each photo pixel looks
    photo = pattern(80 * xy[..., 0] + 32, 80 * xy[..., 1] + 32)
    images = np.repeat(photo[None, ..., None], 3, axis=-1).astype(np.float32)
    masks = (80 * xy[None, ..., 0] + 32) < 32  # the left half of the pinhole view
    out = _undistorted(Scene([cam], images, masks=masks), 1)
    assert out.cameras[0].distortion is None
    np.testing.assert_allclose(out.cameras[0].K, K)
    inner = slice(4, -4)  # pincushion: the pinhole rim maps outside the photo (border pixels repeat there)
    got = np.asarray(out.images)[0, inner, inner, 0]
    np.testing.assert_allclose(got, pattern(u, v)[inner, inner], atol=UNDISTORT_TOL)
    np.testing.assert_array_equal(np.asarray(out.masks)[0, inner, inner], (u < 32)[inner, inner])
    half = _undistorted(Scene([cam], images, masks=masks), 2)  # then downscaled as the loaders do
    assert np.asarray(half.images).shape == (1, 32, 32, 3) and half.cameras[0].width == 32


def test_photo_folders_are_detected(tmp_path):
    """Detect images directly in a folder, in images/ or in image/ (IDR layout) as photos; the model goes beside."""
    from wtopo.loaders.sfm import find_photos

    for layout in ("flat", "images", "image"):
        root = tmp_path / layout
        folder = root if layout == "flat" else root / layout
        _noise_photos(folder, 2, size=(16, 12))
        (root / "notes.txt").write_text("not a photo")
        assert detect_format(root) == "photos"
        found, names = find_photos(root)
        assert found == str(folder) and names == ["noise_00.png", "noise_01.png"]
    os.makedirs(tmp_path / "none")
    (tmp_path / "none" / "notes.txt").write_text("not a photo")
    with pytest.raises(ValueError, match="image files in ., images/ or image/"):
        detect_format(tmp_path / "none")
