# SPDX-License-Identifier: Apache-2.0
"""Dataset readers: small datasets written in each format; loaded cameras must equal those written."""

import json
import math
import os
import struct

import numpy as np
import pytest
import trimesh
from PIL import Image

from wtopo import Camera, load_scene
from wtopo.loaders import detect_format
from wtopo.loaders.dtu import decompose_projection, rq

CAM_TOL = 1e-9  # float64 round trips through text / binary / matrix inversion
W, H = 24, 18


def _png(path, rgb, alpha=None):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    a = (np.asarray(rgb) * 255 + 0.5).astype(np.uint8)
    if alpha is not None:
        a = np.concatenate([a, (np.asarray(alpha) * 255 + 0.5).astype(np.uint8)[..., None]], axis=-1)
    Image.fromarray(a).save(path)


def _random_pose(rng, i):
    """A camera ~4 units from the origin looking roughly at it, as world-to-camera [4, 4]."""
    eye = rng.normal(size=3)
    eye = 4 * eye / np.linalg.norm(eye)
    c = Camera.look_at(eye, rng.normal(size=3) * 0.2, [0, 0, 1], fov_x=0.9, width=W, height=H)
    return c.world_to_camera


def _rotmat_to_qvec(R):
    # Shepperd's method, w first (Hamilton), as COLMAP writes it
    t = np.trace(R)
    if t > 0:
        s = 0.5 / math.sqrt(t + 1)
        q = [0.25 / s, (R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s, (R[1, 0] - R[0, 1]) * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    return np.array(q)


# -- COLMAP writers (independent of the reader; layout from COLMAP doc/format.rst) -----------------
_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}


def _write_colmap(model_dir, cams, imgs, pts, binary):
    """cams: {id: (model, w, h, params)}; imgs: {id: (qvec, tvec, cam_id, name)}; pts: (xyz, rgb uint8)."""
    os.makedirs(model_dir, exist_ok=True)
    if binary:
        with open(os.path.join(model_dir, "cameras.bin"), "wb") as fh:
            fh.write(struct.pack("<Q", len(cams)))
            for cid, (model, w, h, params) in cams.items():
                model_id = _MODEL_IDS.get(model, model if isinstance(model, int) else -1)
                fh.write(struct.pack("<iiQQ", cid, model_id, w, h))
                fh.write(struct.pack("<" + "d" * len(params), *params))
        with open(os.path.join(model_dir, "images.bin"), "wb") as fh:
            fh.write(struct.pack("<Q", len(imgs)))
            for iid, (q, t, cid, name) in imgs.items():
                fh.write(struct.pack("<i4d3di", iid, *q, *t, cid))
                fh.write(name.encode() + b"\x00")
                fh.write(struct.pack("<Q", 2))
                fh.write(struct.pack("<ddqddq", 1.0, 2.0, -1, 3.0, 4.0, 7))
        with open(os.path.join(model_dir, "points3D.bin"), "wb") as fh:
            xyz, rgb = pts
            fh.write(struct.pack("<Q", len(xyz)))
            for k, (p, c) in enumerate(zip(xyz, rgb)):
                fh.write(struct.pack("<Q3d3Bd", 100 + 3 * k, *p, *c, 0.5))
                fh.write(struct.pack("<Q", 1) + struct.pack("<ii", 1, 0))
    else:
        with open(os.path.join(model_dir, "cameras.txt"), "w") as fh:
            fh.write("# Camera list with one line of data per camera:\n")
            for cid, (model, w, h, params) in cams.items():
                fh.write(f"{cid} {model} {w} {h} " + " ".join(repr(float(p)) for p in params) + "\n")
        with open(os.path.join(model_dir, "images.txt"), "w") as fh:
            fh.write("# Image list with two lines of data per image:\n")
            for iid, (q, t, cid, name) in imgs.items():
                fh.write(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}\n")
                fh.write("1.0 2.0 -1 3.0 4.0 7\n")
        with open(os.path.join(model_dir, "points3D.txt"), "w") as fh:
            xyz, rgb = pts
            for k, (p, c) in enumerate(zip(xyz, rgb)):
                xyz_text = " ".join(repr(float(v)) for v in p)
                fh.write(f"{100 + 3 * k} {xyz_text} {c[0]} {c[1]} {c[2]} 0.5 1 0\n")


_COLMAP_CASES = [  # model, params, expected K entries (fx, fy, cx, cy), expected distortion
    ("SIMPLE_PINHOLE", [30.0, 12.0, 9.0], (30, 30, 12, 9), None),
    ("PINHOLE", [31.0, 29.0, 11.5, 9.5], (31, 29, 11.5, 9.5), None),
    ("SIMPLE_RADIAL", [28.0, 12.2, 8.8, -0.05], (28, 28, 12.2, 8.8), [-0.05, 0, 0, 0, 0]),
    ("RADIAL", [27.0, 12.0, 9.0, 0.02, -0.01], (27, 27, 12, 9), [0.02, -0.01, 0, 0, 0]),
    ("OPENCV", [30.5, 30.1, 12.3, 8.7, 0.03, -0.02, 0.001, -0.002], (30.5, 30.1, 12.3, 8.7),
     [0.03, -0.02, 0.001, -0.002, 0]),
]


def _colmap_dataset(root, binary, rng, cases=_COLMAP_CASES):
    cams, imgs, want = {}, {}, {}
    for k, (model, params, _, _) in enumerate(cases):
        cid, iid = 10 + 7 * k, 500 - 13 * k  # non-contiguous ids, as COLMAP writes them
        w2c = _random_pose(rng, k)
        name = f"img_{k:02d}.png"
        cams[cid] = (model, W, H, params)
        imgs[iid] = (_rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3], cid, name)
        _png(os.path.join(root, "images", name), rng.random((H, W, 3)))
        want[name] = w2c
    xyz = rng.normal(size=(20, 3))
    rgb = rng.integers(0, 256, size=(20, 3))
    _write_colmap(os.path.join(root, "sparse", "0"), cams, imgs, (xyz, rgb), binary)
    return want, xyz, rgb


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_cameras_equal_written(tmp_path, binary):
    """Read a COLMAP model (text or binary) with every supported camera model and compare cameras."""
    rng = np.random.default_rng(1)
    want, xyz, rgb = _colmap_dataset(str(tmp_path), binary, rng)
    assert detect_format(str(tmp_path)) == "colmap"
    s = load_scene(tmp_path)
    assert [c.name for c in s.cameras] == sorted(want)  # sorted by name
    for cam, (_, _, (fx, fy, cx, cy), dist) in zip(s.cameras, _COLMAP_CASES):
        np.testing.assert_allclose(cam.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], atol=CAM_TOL)
        np.testing.assert_allclose(cam.world_to_camera, want[cam.name], atol=CAM_TOL)
        assert (cam.width, cam.height) == (W, H)
        if dist is None:
            assert cam.distortion is None
        else:
            np.testing.assert_allclose(cam.distortion, dist, atol=CAM_TOL)
    np.testing.assert_allclose(s.points, xyz, atol=CAM_TOL)
    np.testing.assert_allclose(s.point_colors, rgb / 255.0, atol=CAM_TOL)
    assert s.images.shape == (5, H, W, 3) and s.masks is None


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", 99])
def test_colmap_unsupported_model_says_undistort(tmp_path, binary, model):
    """Refuse fisheye and unknown camera models with the image_undistorter hint."""
    if model == 99 and not binary:
        model = "THIN_PRISM_FISHEYE"
    rng = np.random.default_rng(2)
    _colmap_dataset(str(tmp_path), binary, rng, cases=[(model, [30.0] * 8, None, None)])
    with pytest.raises(ValueError, match="image_undistorter"):
        load_scene(tmp_path)


def test_colmap_nan_pose_names_the_camera(tmp_path):
    """Report a NaN translation with the camera index and image name."""
    rng = np.random.default_rng(3)
    root = str(tmp_path)
    w2c = _random_pose(rng, 0)
    _png(os.path.join(root, "images", "a.png"), rng.random((H, W, 3)))
    _png(os.path.join(root, "images", "b.png"), rng.random((H, W, 3)))
    q = _rotmat_to_qvec(w2c[:3, :3])
    imgs = {1: (q, w2c[:3, 3], 1, "a.png"), 2: (q, [0.0, np.nan, 1.0], 1, "b.png")}
    _write_colmap(os.path.join(root, "sparse", "0"), {1: ("PINHOLE", W, H, [30.0, 30, 12, 9])}, imgs,
                  (np.zeros((0, 3)), np.zeros((0, 3), int)), binary=True)
    with pytest.raises(ValueError, match=r"camera 1 \('b.png'\).*finite.*nan"):
        load_scene(tmp_path)


def _gl_c2w(w2c):
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1
    return c2w


@pytest.mark.parametrize("background, bg_value", [(None, 1.0), ("black", 0.0)])
def test_blender_nerf_synthetic(tmp_path, background, bg_value):
    """Read NeRF-synthetic transforms (camera_angle_x, OpenGL c2w, RGBA without extension)."""
    rng = np.random.default_rng(4)
    angle = 0.69
    frames = {"train": [], "test": []}
    want = []
    for split, n in (("train", 3), ("test", 2)):
        for k in range(n):
            w2c = _random_pose(rng, k)
            rgb, alpha = rng.random((H, W, 3)), (rng.random((H, W)) > 0.5).astype(float)
            _png(os.path.join(tmp_path, split, f"r_{k}.png"), rgb, alpha)
            frames[split].append({"file_path": f"./{split}/r_{k}", "rotation": 0.0,
                                  "transform_matrix": _gl_c2w(w2c).tolist()})
            want.append((w2c, np.round(rgb * 255) / 255, alpha > 0.5))
    for split, fr in frames.items():
        with open(os.path.join(tmp_path, f"transforms_{split}.json"), "w") as fh:
            json.dump({"camera_angle_x": angle, "frames": fr}, fh)
    s = load_scene(tmp_path, background=background)
    f = 0.5 * W / math.tan(0.5 * angle)
    assert s.train_indices.tolist() == [0, 1, 2] and s.test_indices.tolist() == [3, 4]
    assert s.background == (bg_value,) * 3
    for cam, (w2c, rgb, mask), img, m in zip(s.cameras, want, s.images.numpy(), s.masks.numpy()):
        np.testing.assert_allclose(cam.K, [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], atol=CAM_TOL)
        np.testing.assert_allclose(cam.world_to_camera, w2c, atol=CAM_TOL)
        np.testing.assert_array_equal(m, mask)
        np.testing.assert_allclose(img[mask], rgb[mask], atol=1e-6)
        np.testing.assert_allclose(img[~mask], bg_value, atol=1e-6)
    half = load_scene(tmp_path, background=background, downscale=2)
    assert half.images.shape == (5, H // 2, W // 2, 3) and half.masks.shape == (5, H // 2, W // 2)
    np.testing.assert_allclose(half.cameras[0].K[:2], s.cameras[0].K[:2] / 2, atol=CAM_TOL)
    # a camera at +4 z with the identity OpenGL rotation looks down -z at the origin
    cam_gl = np.eye(4)
    cam_gl[2, 3] = 4.0
    with open(os.path.join(tmp_path, "transforms_train.json"), "w") as fh:
        frame = {"file_path": "./train/r_0", "transform_matrix": cam_gl.tolist()}
        json.dump({"camera_angle_x": angle, "frames": [frame]}, fh)
    c = load_scene(tmp_path, splits=("train",)).cameras[0]
    np.testing.assert_allclose(c.center, [0, 0, 4], atol=CAM_TOL)
    np.testing.assert_allclose(c.forward, [0, 0, -1], atol=CAM_TOL)
    uv, z = c.project(np.array([[0.0, 0, 0], [0, 1, 0]]))
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=CAM_TOL)
    assert uv[1, 1] < H / 2  # world +y (Blender's up in this view) is towards the top row


def test_dtu_decomposition_and_units(tmp_path):
    """Decompose DTU world_mat (any projective scale) back to K, pose; bounds from scale_mat in mm."""
    rng = np.random.default_rng(5)
    data, want = {}, []
    scale_mat = np.diag([210.0, 210.0, 210.0, 1.0])
    scale_mat[:3, 3] = [-12.0, 40.0, 620.0]
    for i in range(3):
        K = np.array([[2890.0 + i, 0.3, 820.5], [0, 2885.0, 600.2], [0, 0, 1]]) / 64  # small image
        K[2, 2] = 1
        w2c = _random_pose(rng, i)
        w2c[:3, 3] *= 150.0  # millimetres
        P = np.eye(4)
        P[:3, :4] = K @ w2c[:3, :4]
        P *= (-1) ** i * (0.5 + i)  # projective scale, including negative
        data[f"world_mat_{i}"] = P
        data[f"scale_mat_{i}"] = scale_mat
        want.append((K, w2c))
        _png(os.path.join(tmp_path, "image", f"{i:06d}.png"), rng.random((H, W, 3)))
        m = np.zeros((H, W))
        m[4:10, 5:15] = 1
        _png(os.path.join(tmp_path, "mask", f"{i:03d}.png"), np.repeat(m[..., None], 3, axis=2))
    np.savez(os.path.join(tmp_path, "cameras_sphere.npz"), **data)
    s = load_scene(tmp_path)
    for cam, (K, w2c) in zip(s.cameras, want):
        np.testing.assert_allclose(cam.K, K, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(cam.world_to_camera, w2c, rtol=1e-10, atol=1e-7)
    np.testing.assert_allclose(s.bounds[0], scale_mat[:3, 3] - 210)
    np.testing.assert_allclose(s.bounds[1], scale_mat[:3, 3] + 210)
    np.testing.assert_allclose(s.info["scale_mat"], scale_mat)
    assert s.masks.shape == (3, H, W) and s.masks[:, 4:10, 5:15].all() and s.masks.sum() == 3 * 60
    # the normalisation maps the scale_mat sphere's box into the unit cube
    sim = s.normalization(margin=0.0)
    np.testing.assert_allclose(sim.to_internal(np.stack(s.bounds)), [[0, 0, 0], [1, 1, 1]], atol=1e-12)


def test_rq_decomposition():
    """Factor random matrices as upper-triangular (positive diagonal) times orthogonal."""
    rng = np.random.default_rng(6)
    for _ in range(20):
        M = rng.normal(size=(3, 3))
        U, Q = rq(M)
        np.testing.assert_allclose(U @ Q, M, atol=1e-12)
        np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.tril(U, -1), 0, atol=1e-12)
        assert np.all(np.diag(U) > 0)
    K, w2c = decompose_projection(-3.0 * np.array([[100, 0, 10, 5], [0, 90, 20, 6], [0, 0, 1, 7.0]]))
    np.testing.assert_allclose(K, [[100, 0, 10], [0, 90, 20], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(w2c[:3, 3], np.linalg.solve(K, [5, 6, 7.0]), atol=1e-12)
    np.testing.assert_allclose(w2c[:3, :3], np.eye(3), atol=1e-12)


def test_nerfstudio_shared_and_per_frame_intrinsics(tmp_path):
    """Read nerfstudio transforms.json with shared and per-frame intrinsics, distortion, masks, split, ply."""
    rng = np.random.default_rng(7)
    frames, want = [], []
    for k in range(4):
        w2c = _random_pose(rng, k)
        fr = {"file_path": f"images/frame_{k:05d}.png", "transform_matrix": _gl_c2w(w2c)[:3].tolist()}
        _png(os.path.join(tmp_path, fr["file_path"]), rng.random((H, W, 3)))
        K = np.array([[25.0, 0, 11.8], [0, 26.0, 9.3], [0, 0, 1]])
        dist = [0.01, -0.02, 0.003, 0.001, 0.0005]
        if k == 2:  # per-frame override
            fr.update({"fl_x": 27.5, "fl_y": 27.0, "cx": 12.5, "cy": 8.5, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
                       "k3": 0.0})
            K = np.array([[27.5, 0, 12.5], [0, 27.0, 8.5], [0, 0, 1]])
            dist = None
        m = np.zeros((H, W))
        m[k:k + 5, 2:9] = 1
        fr["mask_path"] = f"masks/frame_{k:05d}.png"
        _png(os.path.join(tmp_path, fr["mask_path"]), np.repeat(m[..., None], 3, axis=2))
        frames.append(fr)
        want.append((K, w2c, dist, m > 0.5))
    pts = rng.normal(size=(30, 3))
    trimesh.PointCloud(pts, colors=np.full((30, 4), 200, np.uint8)).export(os.path.join(tmp_path, "points.ply"))
    meta = {"camera_model": "OPENCV", "fl_x": 25.0, "fl_y": 26.0, "cx": 11.8, "cy": 9.3, "w": W, "h": H,
            "k1": 0.01, "k2": -0.02, "p1": 0.003, "p2": 0.001, "k3": 0.0005, "frames": frames,
            "ply_file_path": "points.ply",
            "train_filenames": [f["file_path"] for f in frames[:3]], "test_filenames": [frames[3]["file_path"]]}
    with open(os.path.join(tmp_path, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    s = load_scene(tmp_path)
    for cam, (K, w2c, dist, mask), m in zip(s.cameras, want, s.masks.numpy()):
        np.testing.assert_allclose(cam.K, K, atol=CAM_TOL)
        np.testing.assert_allclose(cam.world_to_camera, w2c, atol=CAM_TOL)
        assert (cam.width, cam.height) == (W, H)
        if dist is None:
            assert cam.distortion is None
        else:
            np.testing.assert_allclose(cam.distortion, dist, atol=CAM_TOL)
        np.testing.assert_array_equal(m, mask)
    assert s.train_indices.tolist() == [0, 1, 2] and s.test_indices.tolist() == [3]
    np.testing.assert_allclose(s.points, pts, atol=1e-6)  # PLY stores float32
    np.testing.assert_allclose(s.point_colors, 200 / 255, atol=1e-9)
    assert s.bounds is None
    meta.update({"aabb": [[-1.0, -2.0, -0.5], [1.0, 2.0, 1.5]], "aabb_scale": 4})
    with open(os.path.join(tmp_path, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    s = load_scene(tmp_path)  # the dataset's box is the region of interest
    np.testing.assert_array_equal(np.stack(s.bounds), [[-1.0, -2.0, -0.5], [1.0, 2.0, 1.5]])
    assert s.info["aabb_scale"] == 4.0
    meta["aabb"] = [[1.0, 0, 0], [0, 1, 1]]
    with open(os.path.join(tmp_path, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    with pytest.raises(ValueError, match="aabb"):
        load_scene(tmp_path)
    del meta["aabb"]
    meta["camera_model"] = "OPENCV_FISHEYE"
    with open(os.path.join(tmp_path, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    with pytest.raises(ValueError, match="camera_model OPENCV_FISHEYE"):
        load_scene(tmp_path)


def test_detection_errors(tmp_path):
    """Name every format looked for when a folder holds none."""
    with pytest.raises(ValueError, match="COLMAP"):
        load_scene(tmp_path)
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "missing")
    with pytest.raises(ValueError, match="format must be one of"):
        load_scene(tmp_path, format="ply")
