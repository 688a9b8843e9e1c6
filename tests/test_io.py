# SPDX-License-Identifier: Apache-2.0
"""Tests for wtopo.io: 3DGS surfel PLY, mesh export, the USD timeline (written, reopened with pxr)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from wtopo import Camera
from wtopo.io import (
    FLAT_LOG_SCALE,
    HAS_SPLAT_SCHEMA,
    OPACITY_EPS,
    SurfelEvent,
    TimelineVerificationError,
    TimelineWriter,
    export,
    export_mesh,
    read_cameras,
    read_surfels,
    read_surfels_ply,
    read_timeline,
    write_surfels_ply,
)
from wtopo.io import usd as usd_module

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom  # noqa: E402

F32_RTOL = 1e-6  # values pass through float32 once: relative rounding 6e-8, plus log/exp and sigmoid/logit
F16_ATOL = 1e-3  # instancer orientations are quath: 10-bit mantissa, |q| <= 1
K_RTOL = 1e-6  # focal length and apertures are float32 USD attributes
POSE_ATOL = 1e-9  # camera transforms are double-precision xformOps
PIXEL_ATOL = 1e-4  # Gf.Frustum projection vs Camera.project, through the float32 intrinsics, in pixels


def _surfels(rng, n, k=16):
    return dict(means=rng.normal(size=(n, 3)), quats=rng.normal(size=(n, 4)), scales=rng.uniform(0.01, 0.2, (n, 2)),
                opacities=rng.uniform(0, 1, n), colors_or_sh=rng.normal(size=(n, k, 3)) * 0.3)


def _cameras():
    a = Camera.look_at([2.5, 0.3, 1.0], [0, 0, 0], [0, 1, 0], fov_x=0.9, width=64, height=48, name="images/r_0.png")
    b = Camera.look_at([-1.0, 2.0, 2.0], [0.1, 0, 0], [0, 1, 0], fov_x=1.2, width=40, height=30)
    # off-centre principal point and fx != fy, the cases a centred square-pixel test would miss
    b = Camera(np.array([[41.0, 0, 17.5], [0, 37.0, 12.25], [0, 0, 1]]), b.world_to_camera, 40, 30)
    c = Camera(np.array([[50.0, 0.7, 20], [0, 52.0, 16], [0, 0, 1]]), a.world_to_camera, 40, 32,
               distortion=[0.1, -0.02, 0.001, 0.002])
    return [a, b, c]


# Sampled iterations and what each sample holds: the mesh stays, changes topology, moves, is left
# out (held) and moves again, so skipped repeats, topology changes and hold keys are all exercised.
ITERATIONS = [0, 10, 20, 30, 40, 50]


def _meshes():
    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.icosphere(subdivisions=2)
    return {0: (a.vertices, a.faces), 10: (a.vertices, a.faces), 20: (b.vertices, b.faces),
            30: (b.vertices * 1.1, b.faces), 40: None, 50: (b.vertices * 1.2, b.faces)}


def write_timeline(path, *, n_surfels=(40, 40, 55, 60, 60, 70), max_surfels=100_000, splats=True):
    """Write the test timeline; return the writer's stats and the per-iteration surfel inputs."""
    rng = np.random.default_rng(0)
    meshes = _meshes()
    w = TimelineWriter(path, up_axis="Z", meters_per_unit=0.001, time_codes_per_second=50.0,
                       max_surfels=max_surfels, splats=splats, splat_sh_degree=None)
    w.add_cameras(_cameras())
    gt = trimesh.creation.icosphere(subdivisions=3)
    w.add_mesh("ground_truth", gt.vertices, gt.faces)
    surfels = {}
    for it, n in zip(ITERATIONS, n_surfels):
        s = _surfels(rng, n)
        s["events"] = rng.choice([0, SurfelEvent.SPAWNED, SurfelEvent.PRUNED | SurfelEvent.FLIPPED], n)
        s["distance_to_mesh"] = rng.uniform(0, 0.1, n)
        s["point_weight"] = rng.uniform(0.5, 1, n)
        surfels[it] = s
        m = meshes[it]
        w.add_sample(it, **s, **({} if m is None else dict(mesh_verts=m[0], mesh_faces=m[1])))
    w.add_mesh("final", meshes[50][0], meshes[50][1])
    return w.close(), surfels


@pytest.fixture(scope="module")
def timeline(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("timeline") / "timeline.usdc")
    stats, surfels = write_timeline(path)
    return path, stats, surfels


# -- PLY ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [1, 4, 16])
def test_surfel_ply_round_trip(tmp_path, k):
    """Write surfels with SH of K coefficients and read back the same parameters."""
    rng = np.random.default_rng(1)
    s = _surfels(rng, 33, k)
    path = write_surfels_ply(tmp_path / "s.ply", **s)
    r = read_surfels_ply(path)
    q = s["quats"] / np.linalg.norm(s["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(r.means, s["means"], rtol=F32_RTOL, atol=1e-7)
    np.testing.assert_allclose(r.quats, q, rtol=F32_RTOL, atol=1e-7)
    np.testing.assert_allclose(r.scales, s["scales"], rtol=10 * F32_RTOL)
    np.testing.assert_allclose(r.opacities, s["opacities"], atol=2 * OPACITY_EPS)
    np.testing.assert_allclose(r.sh, s["colors_or_sh"], rtol=F32_RTOL, atol=1e-7)
    assert r.sh_degree == int(np.sqrt(k)) - 1


def test_surfel_ply_rgb_colors_and_torch_inputs(tmp_path):
    """Accept float64 torch tensors and RGB colours, which come back through the DC term."""
    rng = np.random.default_rng(2)
    s = _surfels(rng, 20)
    rgb = rng.uniform(0, 1, (20, 3))
    args = {k: torch.as_tensor(v) for k, v in s.items() if k != "colors_or_sh"}
    r = read_surfels_ply(write_surfels_ply(tmp_path / "s.ply", **args, colors_or_sh=torch.as_tensor(rgb)))
    assert r.sh.shape == (20, 1, 3)
    np.testing.assert_allclose(r.colors, rgb, atol=1e-6)


def test_surfel_ply_extreme_values_are_finite(tmp_path):
    """Write opacity exactly 0 and 1 and zero scales as finite numbers."""
    rng = np.random.default_rng(3)
    s = _surfels(rng, 4, 1)
    s["opacities"] = np.array([0.0, 1.0, 0.5, 1.0])
    s["scales"][0] = 0.0
    path = write_surfels_ply(tmp_path / "s.ply", **s)
    raw = np.fromfile(path, dtype=np.uint8)
    body = raw[raw.tobytes().index(b"end_header\n") + len(b"end_header\n"):].view("<f4")
    assert np.all(np.isfinite(body))
    r = read_surfels_ply(path)
    np.testing.assert_allclose(r.opacities, s["opacities"], atol=2 * OPACITY_EPS)
    assert np.all(np.isfinite(r.scales)) and r.scales[0].max() < 1e-6


def test_surfel_ply_readable_by_trimesh_and_open3d(tmp_path):
    """Open the surfel PLY with trimesh and Open3D and find the 3DGS attributes in order."""
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(4)
    s = _surfels(rng, 25, 16)
    path = str(write_surfels_ply(tmp_path / "s.ply", **s))
    pc = trimesh.load(path)
    np.testing.assert_allclose(pc.vertices, s["means"], rtol=F32_RTOL, atol=1e-7)
    legacy = o3d.io.read_point_cloud(path)
    assert legacy.has_normals()
    np.testing.assert_allclose(np.asarray(legacy.points), s["means"], rtol=F32_RTOL, atol=1e-7)
    t = o3d.t.io.read_point_cloud(path).point
    sh = s["colors_or_sh"]
    np.testing.assert_allclose(t["f_rest_0"].numpy()[:, 0], sh[:, 1, 0], rtol=F32_RTOL, atol=1e-7)
    np.testing.assert_allclose(t["f_rest_15"].numpy()[:, 0], sh[:, 1, 1], rtol=F32_RTOL, atol=1e-7)  # channel-major
    np.testing.assert_allclose(t["scale_2"].numpy()[:, 0], FLAT_LOG_SCALE, rtol=F32_RTOL)
    w = s["quats"][:, 0] / np.linalg.norm(s["quats"], axis=1)
    np.testing.assert_allclose(t["rot_0"].numpy()[:, 0], w, rtol=F32_RTOL, atol=1e-7)  # w first
    with open(path, "rb") as f:
        header = f.read(2000).split(b"end_header")[0].decode()
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def test_surfel_ply_rejects_bad_arrays(tmp_path):
    """Reject logit opacities, log scales, NaN means and wrong shapes, naming the argument."""
    rng = np.random.default_rng(5)
    s = _surfels(rng, 5, 1)
    for key, bad, msg in [("opacities", s["opacities"] * 10 - 5, "opacities"), ("scales", -s["scales"], "scales"),
                          ("means", np.full((5, 3), np.nan), "means"), ("quats", np.ones((5, 3)), "quats"),
                          ("colors_or_sh", np.ones((5, 3, 3)), "colors_or_sh")]:
        with pytest.raises(ValueError, match=msg):
            write_surfels_ply(tmp_path / "s.ply", **{**s, key: bad})
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_export_mesh_round_trip(tmp_path, suffix):
    """Write a mesh as PLY / OBJ and read the same vertices and faces with trimesh."""
    m = trimesh.creation.icosphere(subdivisions=1)
    path = export_mesh((torch.as_tensor(m.vertices), torch.as_tensor(m.faces)), tmp_path / f"m{suffix}")
    r = trimesh.load(path, process=False)
    np.testing.assert_allclose(r.vertices, m.vertices, atol=1e-6)
    np.testing.assert_array_equal(r.faces, m.faces)


# -- USD timeline -------------------------------------------------------------------------------
def test_timeline_stage_metadata(timeline):
    """Author up axis, metersPerUnit, timeCodesPerSecond and the start/end time codes."""
    path, stats, _ = timeline
    stage = Usd.Stage.Open(path)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert stage.GetRootLayer().HasTimeCodesPerSecond() and stage.GetTimeCodesPerSecond() == 50.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 50.0)
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert stats.samples == len(ITERATIONS) and stats.bytes == os.path.getsize(path)
    assert stats.bytes_per_100_samples == pytest.approx(100 * stats.bytes / len(ITERATIONS))


def test_timeline_proxy_mesh_topology_varies(timeline):
    """Time-sample one proxy mesh whose topology changes, without repeats or GeomSubsets."""
    path, _, _ = timeline
    stage = Usd.Stage.Open(path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ProxyMesh"))
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    assert not [c for c in mesh.GetPrim().GetChildren() if c.IsA(UsdGeom.Subset)]
    # repeated mesh at 10 skipped; 40 is the hold key written because 50 moved the same topology
    assert mesh.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0, 20.0]
    assert mesh.GetPointsAttr().GetTimeSamples() == [0.0, 20.0, 30.0, 40.0, 50.0]
    counts = {len(mesh.GetFaceVertexIndicesAttr().Get(t)) for t in (0, 20)}
    assert len(counts) == 2
    meshes = _meshes()
    held = meshes[30]
    for it in ITERATIONS:
        want = meshes[it] if meshes[it] is not None else held
        np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(it)), want[0], rtol=F32_RTOL, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get(it)).reshape(-1, 3), want[1])
        n = np.asarray(mesh.GetNormalsAttr().Get(it))
        assert n.shape == want[0].shape and np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
        ext = np.asarray(mesh.GetExtentAttr().Get(it))
        np.testing.assert_allclose(ext, [want[0].min(0), want[0].max(0)], rtol=F32_RTOL, atol=1e-7)
    # between 30 and 40 the mesh holds (the hold key stops interpolation towards 50)
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(35)), held[0], rtol=F32_RTOL, atol=1e-7)


def test_timeline_surfels_per_sample(timeline):
    """Write the surfels at every sample with consistent lengths, finite values and the given primvars."""
    path, _, surfels = timeline
    stage = Usd.Stage.Open(path)
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Surfels"))
    pv = UsdGeom.PrimvarsAPI(inst)
    proto = inst.GetPrototypesRel().GetTargets()
    assert len(proto) == 1 and stage.GetPrimAtPath(proto[0]).IsA(UsdGeom.Mesh)
    assert inst.GetPositionsAttr().GetTimeSamples() == [float(i) for i in ITERATIONS]
    assert inst.GetProtoIndicesAttr().GetNumTimeSamples() == len({len(s["means"]) for s in surfels.values()})
    for it, s in surfels.items():
        n = len(s["means"])
        pos = np.asarray(inst.GetPositionsAttr().Get(it))
        np.testing.assert_allclose(pos, s["means"], rtol=F32_RTOL, atol=1e-7)
        xyzw = np.asarray(inst.GetOrientationsAttr().Get(it), dtype=np.float64)
        q = s["quats"] / np.linalg.norm(s["quats"], axis=1, keepdims=True)
        np.testing.assert_allclose(xyzw[:, [3, 0, 1, 2]], q, atol=F16_ATOL)
        np.testing.assert_allclose(np.asarray(inst.GetScalesAttr().Get(it))[:, :2], s["scales"], rtol=F32_RTOL)
        assert len(inst.GetProtoIndicesAttr().Get(it)) == n
        for name, key in [("opacity", "opacities"), ("weight", "point_weight"),
                          ("distance_to_mesh", "distance_to_mesh")]:
            primvar = pv.GetPrimvar(name)
            assert primvar.GetInterpolation() == UsdGeom.Tokens.vertex
            np.testing.assert_allclose(np.asarray(primvar.Get(it)), s[key], rtol=F32_RTOL, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(pv.GetPrimvar("events").Get(it)), s["events"])
        colors = np.asarray(pv.GetPrimvar("displayColor").Get(it))
        assert colors.shape == (n, 3) and np.all(np.isfinite(colors)) and colors.min() >= 0 and colors.max() <= 1


@pytest.mark.skipif(not HAS_SPLAT_SCHEMA, reason="usd-core without UsdVol.ParticleField3DGaussianSplat")
def test_timeline_gaussian_splats(timeline):
    """Write linear splat values and particle-major SH coefficients to the ParticleField prim."""
    from pxr import UsdVol

    from wtopo.io.usd import FLAT_SCALE

    path, _, surfels = timeline
    stage = Usd.Stage.Open(path)
    sp = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/World/Splats"))
    assert sp.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 3
    for it, s in surfels.items():
        n = len(s["means"])
        np.testing.assert_allclose(np.asarray(sp.GetOpacitiesAttr().Get(it)), s["opacities"], rtol=F32_RTOL)
        scales = np.asarray(sp.GetScalesAttr().Get(it))
        np.testing.assert_allclose(scales[:, :2], s["scales"], rtol=F32_RTOL)
        np.testing.assert_allclose(scales[:, 2], FLAT_SCALE, rtol=F32_RTOL)
        sh = np.asarray(sp.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(it)).reshape(n, 16, 3)
        np.testing.assert_allclose(sh, s["colors_or_sh"], rtol=F32_RTOL, atol=1e-7)
    r = read_surfels(path, 35)  # latest sample at or before 35 is 30
    np.testing.assert_allclose(r.sh, surfels[30]["colors_or_sh"], rtol=F32_RTOL, atol=1e-7)


@pytest.mark.skipif(not HAS_SPLAT_SCHEMA, reason="usd-core without UsdVol.ParticleField3DGaussianSplat")
def test_timeline_splats_keep_dc_by_default(tmp_path):
    """Keep only the SH DC term in the splats unless asked for more."""
    from pxr import UsdVol

    s = _surfels(np.random.default_rng(7), 6, 16)
    w = TimelineWriter(tmp_path / "t.usdc")
    w.add_sample(0, **s)
    w.close()
    stage = Usd.Stage.Open(str(tmp_path / "t.usdc"))
    sp = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/World/Splats"))
    assert sp.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 0
    np.testing.assert_allclose(np.asarray(sp.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(0)),
                               s["colors_or_sh"][:, 0], rtol=F32_RTOL, atol=1e-7)


def test_timeline_cameras_round_trip(timeline):
    """Read the cameras back to the same K and world_to_camera, and project like pxr's own frustum."""
    path, _, _ = timeline
    cams = _cameras()
    back = read_cameras(path)
    assert len(back) == len(cams)
    for c, r in zip(cams, back):
        np.testing.assert_allclose(r.K, c.K, rtol=K_RTOL, atol=1e-9)
        np.testing.assert_allclose(r.world_to_camera, c.world_to_camera, atol=POSE_ATOL)
        assert (r.width, r.height) == (c.width, c.height)
        if c.distortion is None:
            assert r.distortion is None
        else:
            np.testing.assert_allclose(r.distortion, c.distortion)
    assert back[0].name == "images/r_0.png"
    stage = Usd.Stage.Open(path)
    prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    pts = np.random.default_rng(6).normal(size=(20, 3)) * 0.3
    for prim, c in zip(prims[:2], cams[:2]):  # no skew, no distortion: plain USD projection applies
        op = UsdGeom.Xformable(prim).GetOrderedXformOps()[0]
        assert op.GetPrecision() == UsdGeom.XformOp.PrecisionDouble
        frustum = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default()).frustum
        m = np.array(frustum.ComputeViewMatrix() * frustum.ComputeProjectionMatrix())  # row-vector convention
        h = np.c_[pts, np.ones(len(pts))] @ m
        ndc = h[:, :3] / h[:, 3:]
        uv_usd = np.stack([(ndc[:, 0] + 1) / 2 * c.width, (1 - ndc[:, 1]) / 2 * c.height], 1)
        np.testing.assert_allclose(uv_usd, c.project(pts)[0], atol=PIXEL_ATOL)


def test_timeline_camera_images(tmp_path):
    """Save the camera images as PNG beside the timeline and reference them from the cameras."""
    from PIL import Image

    cams = _cameras()[:2]
    images = [np.random.default_rng(8).uniform(0, 1, (c.height, c.width, 3)) for c in cams]
    w = TimelineWriter(tmp_path / "t.usdc")
    paths = w.add_cameras(cams, images)
    w.close()
    stage = Usd.Stage.Open(str(tmp_path / "t.usdc"))
    for p, img in zip(paths, images):
        asset = stage.GetPrimAtPath(p).GetAttribute("wtopo:image").Get()
        png = np.asarray(Image.open(tmp_path / asset.path))
        np.testing.assert_allclose(png / 255.0, img, atol=0.5 / 255 + 1e-9)  # 8-bit rounding
    with pytest.raises(ValueError, match="one image per camera"):
        TimelineWriter(tmp_path / "u.usdc").add_cameras(cams, images[:1])


def test_timeline_verification_failure_leaves_nothing(tmp_path, monkeypatch):
    """Raise when the saved file is empty of prims, leaving neither the target nor a temp file."""
    target = tmp_path / "timeline.usdc"

    def broken_export(layer, path):  # OpenUSD#3659: Save() reports success, the file holds nothing
        Sdf.Layer.CreateAnonymous(".usdc").Export(path)

    monkeypatch.setattr(usd_module, "_export_layer", broken_export)
    with pytest.raises(TimelineVerificationError, match="prims"):
        write_timeline(str(target), n_surfels=(5,) * 6)
    assert os.listdir(tmp_path) == []


def test_timeline_verification_failure_keeps_previous_file(tmp_path, monkeypatch):
    """Keep the last good file when a later flush fails verification."""
    target = str(tmp_path / "timeline.usdc")
    w = TimelineWriter(target)
    m = trimesh.creation.icosphere(subdivisions=1)
    w.add_sample(0, mesh_verts=m.vertices, mesh_faces=m.faces)
    w.flush()
    before = Path(target).read_bytes()
    w.add_sample(5, mesh_verts=m.vertices * 2, mesh_faces=m.faces)
    monkeypatch.setattr(usd_module, "_export_layer", lambda layer, path: Path(path).write_bytes(b""))
    with pytest.raises(TimelineVerificationError, match="empty"):
        w.flush()
    assert Path(target).read_bytes() == before and sorted(os.listdir(tmp_path)) == ["timeline.usdc"]


def test_timeline_decimates_above_cap(tmp_path):
    """Write an evenly strided subset when a sample holds more surfels than max_surfels."""
    path = str(tmp_path / "t.usdc")
    _, surfels = write_timeline(path, n_surfels=(25,) * 6, max_surfels=10, splats=False)
    stage = Usd.Stage.Open(path)
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Surfels"))
    pos = np.asarray(inst.GetPositionsAttr().Get(0))
    idx = np.linspace(0, 24, 10).round().astype(int)
    np.testing.assert_allclose(pos, surfels[0]["means"][idx], rtol=F32_RTOL, atol=1e-7)
    assert not stage.GetPrimAtPath("/World/Splats")


def test_timeline_unchanged_samples_cost_little(tmp_path):
    """Grow the file by far less than a sample's data when the mesh does not change."""
    m = trimesh.creation.icosphere(subdivisions=3)
    sizes = []
    for n in (1, 21):
        w = TimelineWriter(tmp_path / f"t{n}.usdc")
        for it in range(n):
            w.add_sample(it, mesh_verts=m.vertices, mesh_faces=m.faces)
        sizes.append(w.close().bytes)
    assert sizes[1] < sizes[0] * 1.1


def test_timeline_empty_mesh_and_no_surfels(tmp_path):
    """Write and verify samples with an empty mesh and zero surfels (marching cubes found nothing)."""
    w = TimelineWriter(tmp_path / "t.usdc")
    w.add_sample(0, mesh_verts=np.zeros((0, 3)), mesh_faces=np.zeros((0, 3), np.int32),
                 **_surfels(np.random.default_rng(9), 0, 1))
    m = trimesh.creation.icosphere(subdivisions=0)
    w.add_sample(1, mesh_verts=m.vertices, mesh_faces=m.faces, **_surfels(np.random.default_rng(9), 3, 1))
    w.close()
    tl = read_timeline(tmp_path / "t.usdc")
    assert [(len(s.faces), s.num_surfels) for s in tl.samples] == [(0, 0), (20, 3)]


def test_timeline_rejects_bad_samples(tmp_path):
    """Reject decreasing iterations, NaN vertices, out-of-range faces and partial surfel arrays."""
    w = TimelineWriter(tmp_path / "t.usdc")
    m = trimesh.creation.icosphere(subdivisions=0)
    w.add_sample(3, mesh_verts=m.vertices, mesh_faces=m.faces)
    with pytest.raises(ValueError, match="increase"):
        w.add_sample(3, mesh_verts=m.vertices, mesh_faces=m.faces)
    bad = m.vertices.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="mesh_verts"):
        w.add_sample(4, mesh_verts=bad, mesh_faces=m.faces)
    with pytest.raises(ValueError, match="mesh_faces"):
        w.add_sample(4, mesh_verts=m.vertices[:5], mesh_faces=m.faces)
    with pytest.raises(ValueError, match="together"):
        w.add_sample(4, means=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="iteration"):
        w.add_sample(-1, mesh_verts=m.vertices, mesh_faces=m.faces)
    with pytest.raises(ValueError, match="up_axis"):
        TimelineWriter(tmp_path / "u.usdc", up_axis="X")


def test_read_timeline_and_export(timeline, tmp_path):
    """Read per-sample meshes, static meshes and cameras; export mesh, surfel PLY and usda."""
    path, _, surfels = timeline
    tl = read_timeline(path)
    assert tl.iterations == ITERATIONS and tl.up_axis == "Z" and tl.meters_per_unit == pytest.approx(0.001)
    assert set(tl.meshes) == {"ground_truth", "final"} and len(tl.cameras) == 3
    assert [len(s.faces) for s in tl.samples] == [80, 80, 320, 320, 320, 320]
    assert [s.num_surfels for s in tl.samples] == [len(surfels[i]["means"]) for i in ITERATIONS]
    mesh = trimesh.load(export(path, tmp_path / "final.obj"), process=False)
    assert len(mesh.faces) == 320
    early = trimesh.load(export(path, tmp_path / "early.ply", iteration=15), process=False)
    assert len(early.faces) == 80
    s = read_surfels_ply(export(path, tmp_path / "surfels.ply", "surfels", iteration=20))
    np.testing.assert_allclose(s.means, surfels[20]["means"], rtol=F32_RTOL, atol=1e-7)
    usda = export(os.path.dirname(path), tmp_path / "timeline.usda")
    assert read_timeline(usda).iterations == ITERATIONS
    with pytest.raises(ValueError, match="fmt"):
        export(path, tmp_path / "x.txt")
