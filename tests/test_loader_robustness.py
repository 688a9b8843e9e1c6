# SPDX-License-Identifier: Apache-2.0
"""Dataset readers on imperfect captures: missing image files are skipped with one warning,
intrinsics for another resolution and unreadable images are errors that name the culprit."""

import json
import os
import re
import warnings

import numpy as np
import pytest
from PIL import Image
from test_loaders import CAM_TOL, H, W, _gl_c2w, _png, _random_pose, _rotmat_to_qvec, _write_colmap

from wtopo import load_scene
from wtopo.loaders._common import MIN_IMAGES_AFTER_SKIPPING, PRINCIPAL_POINT_MARGIN

FOCAL = 25.0  # pixels; any positive focal length (the tests vary the principal point and the files)


def _nerfstudio(root, n, *, missing=(), cx=None, jpeg=False, rng=None):
    """``n`` frames in a transforms.json; the images of frames in ``missing`` are not written.
    Returns the world-to-camera poses by file_path."""
    rng = rng or np.random.default_rng(0)
    frames, poses = [], {}
    ext = "jpg" if jpeg else "png"
    for k in range(n):
        w2c = _random_pose(rng, k)
        fp = f"images/frame_{k:03d}.{ext}"
        frames.append({"file_path": fp, "transform_matrix": _gl_c2w(w2c).tolist()})
        poses[fp] = w2c
        if k not in missing:
            _png(os.path.join(root, fp), rng.random((H, W, 3)))
    meta = {"camera_model": "PINHOLE", "fl_x": FOCAL, "fl_y": FOCAL, "cx": W / 2 if cx is None else cx, "cy": H / 2,
            "frames": frames, "train_filenames": [f["file_path"] for f in frames[:-1]],
            "test_filenames": [frames[-1]["file_path"]]}
    with open(os.path.join(root, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    return poses


def _load_warning(path, **kw):
    """Load ``path`` and return (scene, the messages of the UserWarnings it raised)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = load_scene(path, **kw)
    return s, [str(w.message) for w in caught if issubclass(w.category, UserWarning)]


def test_nerfstudio_skips_missing_images_with_one_warning(tmp_path):
    """Skip frames whose image is missing, warn once (count first, files named), keep poses and splits."""
    poses = _nerfstudio(tmp_path, 6, missing=(1, 3))
    s, msgs = _load_warning(tmp_path)
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith("2 of 6 images listed in ") and "transforms.json" in msgs[0]
    assert "images/frame_001.png" in msgs[0] and "images/frame_003.png" in msgs[0]
    assert [c.name for c in s.cameras] == [f"images/frame_{k:03d}.png" for k in (0, 2, 4, 5)]
    for cam in s.cameras:
        np.testing.assert_allclose(cam.world_to_camera, poses[cam.name], atol=CAM_TOL)
    assert s.train_indices.tolist() == [0, 1, 2] and s.test_indices.tolist() == [3]


def test_nerfstudio_complete_dataset_does_not_warn(tmp_path):
    """Load a dataset with every image present without any warning."""
    _nerfstudio(tmp_path, 3)
    s, msgs = _load_warning(tmp_path)
    assert len(s) == 3 and msgs == []


@pytest.mark.parametrize("n, missing", [(3, (0, 2)), (2, (0, 1))])
def test_too_few_images_left_is_an_error(tmp_path, n, missing):
    """Refuse a dataset left with fewer than MIN_IMAGES_AFTER_SKIPPING images (or none), naming the missing files."""
    _nerfstudio(tmp_path, n, missing=missing)
    left = n - len(missing)
    assert left < MIN_IMAGES_AFTER_SKIPPING
    with pytest.raises(ValueError, match=rf"{len(missing)} of {n} images listed in .*transforms.json are missing "
                                         rf".*frame_000.png.*; {left} left, at least {MIN_IMAGES_AFTER_SKIPPING}"):
        load_scene(tmp_path)


def test_warning_lists_at_most_twenty_names(tmp_path):
    """Name the first skipped files and count the rest, so the warning stays one readable line."""
    _nerfstudio(tmp_path, 26, missing=range(2, 26))
    _, msgs = _load_warning(tmp_path)
    assert len(msgs) == 1 and msgs[0].startswith("24 of 26 images")
    assert msgs[0].count("images/frame_") == 20 and msgs[0].endswith("and 4 more")


def test_blender_skips_missing_images(tmp_path):
    """Skip Blender frames whose PNG is missing; split indices follow the frames kept."""
    rng = np.random.default_rng(1)
    for split, n in (("train", 4), ("test", 2)):
        frames = []
        for k in range(n):
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": _gl_c2w(_random_pose(rng, k)).tolist()})
            if not (split == "train" and k == 1):
                _png(os.path.join(tmp_path, split, f"r_{k}.png"), rng.random((H, W, 3)))
        with open(os.path.join(tmp_path, f"transforms_{split}.json"), "w") as fh:
            json.dump({"camera_angle_x": 0.7, "frames": frames}, fh)
    s, msgs = _load_warning(tmp_path)
    assert len(msgs) == 1 and msgs[0].startswith("1 of 6 images") and "./train/r_1" in msgs[0]
    assert s.train_indices.tolist() == [0, 1, 2] and s.test_indices.tolist() == [3, 4]
    assert [c.name for c in s.cameras][:3] == [os.path.join("train", f"r_{k}.png") for k in (0, 2, 3)]


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_skips_missing_images(tmp_path, binary):
    """Skip COLMAP images whose file is missing (text and binary models), warning once."""
    rng = np.random.default_rng(2)
    cams = {3: ("PINHOLE", W, H, [FOCAL, FOCAL, W / 2, H / 2])}
    imgs, poses = {}, {}
    for k in range(4):
        w2c = _random_pose(rng, k)
        name = f"img_{k}.png"
        imgs[40 - 3 * k] = (_rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], 3, name)
        poses[name] = w2c
        if k != 2:
            _png(os.path.join(tmp_path, "images", name), rng.random((H, W, 3)))
    _write_colmap(os.path.join(tmp_path, "sparse", "0"), cams, imgs, (np.zeros((0, 3)), np.zeros((0, 3), int)), binary)
    s, msgs = _load_warning(tmp_path)
    listing = "images.bin" if binary else "images.txt"
    assert len(msgs) == 1 and msgs[0].startswith("1 of 4 images listed in ") and listing in msgs[0]
    assert msgs[0].endswith("img_2.png")
    assert [c.name for c in s.cameras] == ["img_0.png", "img_1.png", "img_3.png"]
    for cam in s.cameras:
        np.testing.assert_allclose(cam.world_to_camera, poses[cam.name], atol=CAM_TOL)


def _dtu(root, n, *, missing=(), scale=1.0, rng=None):
    """IDR-layout scan with numbered images / masks; ``scale`` multiplies K as if calibrated at
    ``scale`` times the image resolution. Returns {number: (K, w2c)}."""
    rng = rng or np.random.default_rng(3)
    data, want = {}, {}
    for i in range(n):
        K = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]])
        K[:2] *= scale
        w2c = _random_pose(rng, i)
        P = np.eye(4)
        P[:3, :4] = K @ w2c[:3, :4]
        data[f"world_mat_{i}"] = P
        data[f"scale_mat_{i}"] = np.eye(4)
        want[i] = (K, w2c)
        if i not in missing:
            _png(os.path.join(root, "image", f"{i:06d}.png"), rng.random((H, W, 3)))
            _png(os.path.join(root, "mask", f"{i:03d}.png"), np.ones((H, W, 3)))
    np.savez(os.path.join(root, "cameras_sphere.npz"), **data)
    return want


def test_dtu_pairs_images_by_number_and_skips_missing(tmp_path):
    """Give each numbered DTU image its own world_mat when one in the middle is missing, and warn once."""
    want = _dtu(tmp_path, 5, missing=(2,))
    s, msgs = _load_warning(tmp_path)
    assert len(msgs) == 1 and msgs[0].startswith("1 of 5 images listed in ") and "world_mat_2" in msgs[0]
    assert [c.name for c in s.cameras] == [f"{i:06d}.png" for i in (0, 1, 3, 4)]
    for cam, i in zip(s.cameras, (0, 1, 3, 4)):  # positional pairing would give image 3 world_mat_2
        np.testing.assert_allclose(cam.K, want[i][0], atol=1e-9)
        np.testing.assert_allclose(cam.world_to_camera, want[i][1], atol=1e-9)
    assert s.masks is not None and bool(s.masks.all())


def _set_principal_point(fmt, root, cx):
    """A two-camera dataset of ``fmt`` whose second camera has principal point (cx, H / 2); returns
    (expected camera name, expected intrinsics file name)."""
    rng = np.random.default_rng(4)
    if fmt == "nerfstudio":
        _nerfstudio(root, 2, rng=rng)
        with open(os.path.join(root, "transforms.json")) as fh:
            meta = json.load(fh)
        meta["frames"][1]["cx"] = cx
        with open(os.path.join(root, "transforms.json"), "w") as fh:
            json.dump(meta, fh)
        return "images/frame_001.png", "transforms.json"
    if fmt == "blender":
        frames = []
        for k in range(2):
            frames.append({"file_path": f"./train/r_{k}", "transform_matrix": _gl_c2w(_random_pose(rng, k)).tolist()})
            _png(os.path.join(root, "train", f"r_{k}.png"), rng.random((H, W, 3)))
        frames[1]["cx"] = cx
        with open(os.path.join(root, "transforms_train.json"), "w") as fh:
            json.dump({"camera_angle_x": 0.7, "frames": frames}, fh)
        return os.path.join("train", "r_1.png"), "transforms_train.json"
    if fmt == "colmap":
        cams = {1: ("PINHOLE", W, H, [FOCAL, FOCAL, W / 2, H / 2]), 2: ("PINHOLE", W, H, [FOCAL, FOCAL, cx, H / 2])}
        imgs = {}
        for k in range(2):
            w2c = _random_pose(rng, k)
            imgs[k + 1] = (_rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], k + 1, f"v{k}.png")
            _png(os.path.join(root, "images", f"v{k}.png"), rng.random((H, W, 3)))
        _write_colmap(os.path.join(root, "sparse", "0"), cams, imgs, (np.zeros((0, 3)), np.zeros((0, 3), int)),
                      binary=False)
        return "v1.png", "cameras.txt"
    _dtu(root, 2, rng=rng)
    data = dict(np.load(os.path.join(root, "cameras_sphere.npz")))
    K, w2c = np.array([[FOCAL, 0, cx], [0, FOCAL, H / 2], [0, 0, 1.0]]), _random_pose(rng, 1)
    data["world_mat_1"] = np.eye(4)
    data["world_mat_1"][:3, :4] = K @ w2c[:3, :4]
    np.savez(os.path.join(root, "cameras_sphere.npz"), **data)
    return "000001.png", "cameras_sphere.npz"


_FORMATS = ["nerfstudio", "blender", "colmap", "dtu"]


@pytest.mark.parametrize("fmt", _FORMATS)
@pytest.mark.parametrize("side", [1, -1])
def test_principal_point_far_outside_is_an_error(tmp_path, fmt, side):
    """Refuse a principal point beyond the margin in every format, naming camera, file and values."""
    m = PRINCIPAL_POINT_MARGIN
    cx = (1 + m) * W + 2.0 if side > 0 else -m * W - 2.0
    name, file = _set_principal_point(fmt, str(tmp_path), cx)
    with pytest.raises(ValueError) as err:
        load_scene(tmp_path)
    msg = str(err.value)
    assert re.search(rf"camera 1 \('?{re.escape(name)}'?\) in \S*{re.escape(file)}", msg), msg
    assert f"(cx, cy) = ({cx:g}, {H / 2:g})" in msg and f"{W}x{H} (WxH)" in msg, msg
    assert "another image resolution" in msg, msg


@pytest.mark.parametrize("fmt", _FORMATS)
def test_principal_point_inside_the_margin_loads(tmp_path, fmt):
    """Accept an off-centre principal point just inside the margin (e.g. a crop of a larger image)."""
    cx = (1 + PRINCIPAL_POINT_MARGIN) * W - 2.0
    _set_principal_point(fmt, str(tmp_path), cx)
    s = load_scene(tmp_path)
    np.testing.assert_allclose(s.cameras[1].K[0, 2], cx, atol=1e-9)


def test_dtu_intrinsics_for_the_full_resolution_are_named(tmp_path):
    """Report DTU world_mats calibrated at 4x the image size (1600 px intrinsics, 400 px images)."""
    _dtu(tmp_path, 3, scale=4.0)
    with pytest.raises(ValueError, match=r"camera 0 \('000000.png'\) in \S*cameras_sphere.npz: principal point "
                                         rf"\(cx, cy\) = \({2 * W:g}, {2 * H:g}\).*another image resolution"):
        load_scene(tmp_path)


def _truncated_jpeg(path, rng):
    Image.fromarray((rng.random((64, 80, 3)) * 255).astype(np.uint8)).save(path, quality=95)
    with open(path, "rb") as fh:
        data = fh.read()
    with open(path, "wb") as fh:
        fh.write(data[: len(data) // 2])


def test_truncated_jpeg_is_an_error_naming_the_file(tmp_path):
    """Report a JPEG cut in half (PIL fails only when decoding pixels) as a ValueError naming it."""
    rng = np.random.default_rng(5)
    _nerfstudio(tmp_path, 3, jpeg=True, rng=rng)
    bad = os.path.join(tmp_path, "images", "frame_001.jpg")
    _truncated_jpeg(bad, rng)
    with Image.open(bad) as im:  # the header still parses: the check must decode the pixels
        assert im.size == (80, 64)
    with pytest.raises(ValueError, match=rf"cannot read image {re.escape(bad)}: .*truncated"):
        load_scene(tmp_path)


def test_not_an_image_is_an_error_naming_the_file(tmp_path):
    """Report a file that is no image at all (a text file named .png) as a ValueError naming it."""
    _nerfstudio(tmp_path, 3)
    bad = os.path.join(tmp_path, "images", "frame_002.png")
    with open(bad, "w") as fh:
        fh.write("not an image")
    with pytest.raises(ValueError, match=rf"cannot read image {re.escape(bad)}"):
        load_scene(tmp_path)


def test_malformed_transforms_are_errors_naming_the_file(tmp_path):
    """Report invalid JSON and a frame without file_path with the file's name, not a KeyError."""
    path = os.path.join(tmp_path, "transforms.json")
    with open(path, "w") as fh:
        fh.write("{\"frames\": [")
    with pytest.raises(ValueError, match=rf"{re.escape(path)} is not valid JSON"):
        load_scene(tmp_path)
    with open(path, "w") as fh:
        json.dump({"fl_x": FOCAL, "frames": [{"transform_matrix": np.eye(4).tolist()}]}, fh)
    with pytest.raises(ValueError, match=rf"{re.escape(path)}: frame 0 has no 'file_path'"):
        load_scene(tmp_path)
