# SPDX-License-Identifier: Apache-2.0
"""BVH mesh ray casting (``wtopo.ops.raycast_mesh``) and nearest-face queries (``closest_faces``)."""

import os
import time

import numpy as np
import pytest
import torch
import trimesh
from reference.raycast import closest_point_reference, raycast_reference

from wtopo import Camera, ops
from wtopo.raycast import MeshRaycaster

# float32 hit search vs float64 reference: depths agree to ~1e-6 relative; 1e-5 leaves room for
# the float32 rays of a 3-unit-distant camera.
DEPTH_RTOL = 1e-5
# Open3D (Embree) and Warp's watertight Woop test break ties on shared edges differently and
# round differently near silhouettes: measured 0-3 differing pixels out of 12288 on the bunny.
MAX_MASK_DISAGREE = 1e-3
MAX_FACE_DISAGREE = 2e-3
# Open3D's t_hit is float32: relative agreement measured ~2e-7, 1e-5 is generous.
O3D_DEPTH_RTOL = 1e-5
# float64 shading of float64 vertices: only rounding of the (float64) plane equation remains.
F64_ATOL = 1e-10
# Barycentrics come from the float32 hit search.
BARY_ATOL = 1e-5
# Gradients: float64 reference autograd vs Warp adjoint of the same formula.
GRAD_RTOL, GRAD_ATOL = 1e-7, 1e-9
# closest_faces queries in float32: distances of O(1) carry ~1e-7 error; 1e-5 leaves margin.
CLOSEST_ATOL = 1e-5
# Vertices whose (averaged) normal is within ~72 degrees of the ray are off the silhouette,
# also on the coarse 320-face mesh.
SILHOUETTE_COS = 0.3
# Pixels whose smallest barycentric weight is below this are near an edge: a finite-difference step
# could move the hit to a neighbouring face there, so they are left out of FD checks.
EDGE_MARGIN = 0.02


def _bunny():
    import warp.examples
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(os.path.join(warp.examples.get_asset_directory(), "bunny.usd"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/root/bunny"))
    v = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    f = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    return v, f


def _sphere(subdivisions, dtype=torch.float64, device="cpu"):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = m.vertices * (1.0 + 0.1 * np.sin(3 * m.vertices[:, :1]))  # not a sphere: normals vary by face
    return (torch.tensor(v, dtype=dtype, device=device), torch.tensor(m.faces, dtype=torch.int32, device=device))


def _front_camera(width=40, height=30, eye=(0.4, 0.3, 3.0)):
    return Camera.look_at(eye, [0, 0, 0], [0, -1, 0], fov_x=0.8, width=width, height=height)


def _grid(n, z=0.0, dtype=torch.float64, device="cpu"):
    """A flat n x n grid of unit quads (2 triangles each) in the plane z, vertices at integers."""
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    v = np.stack([ii.ravel(), jj.ravel(), np.full(ii.size, z)], 1).astype(np.float64)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return torch.tensor(v, dtype=dtype, device=device), torch.tensor(f, dtype=torch.int32, device=device)


def test_matches_open3d_on_bunny(device):
    """Agree with Open3D's RaycastingScene on hit mask, face ids and z-depth for the bunny."""
    o3d = pytest.importorskip("open3d")
    v, f = _bunny()
    cam = Camera.look_at([0.4, 1.0, 2.6], [-0.1, 0.8, 0.0], [0, 1, 0], fov_x=0.9, width=128, height=96)
    out = ops.raycast_mesh(torch.tensor(v, dtype=torch.float32, device=device),
                           torch.tensor(f, dtype=torch.int32, device=device), cam)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    o, d = cam.pixel_rays("cpu", torch.float32)
    ans = scene.cast_rays(o3d.core.Tensor(torch.cat([o, d], -1).numpy()))
    t_ref = ans["t_hit"].numpy()
    mask_ref = np.isfinite(t_ref)
    face_ref = ans["primitive_ids"].numpy().astype(np.int64)
    mask = out.mask.cpu().numpy()
    assert mask_ref.mean() > 0.3, "the bunny must fill a good part of the view"
    assert (mask != mask_ref).mean() <= MAX_MASK_DISAGREE
    both = mask & mask_ref
    face = out.face_id.cpu().numpy()
    assert (face[both] != face_ref[both]).mean() <= MAX_FACE_DISAGREE
    same = both & (face == face_ref)
    np.testing.assert_allclose(out.depth.cpu().numpy()[same], t_ref[same], rtol=O3D_DEPTH_RTOL)
    assert np.all(face[~mask] == -1) and np.all(out.depth.cpu().numpy()[~mask] == 0)
    n = out.normal.cpu().numpy()
    np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1.0, rtol=1e-5)
    assert np.all(n[~mask] == 0)


def test_matches_torch_reference_float64(device):
    """Match the brute-force Moller-Trumbore reference in float64: depth, normal, face id, barycentrics."""
    verts, faces = _sphere(2, device=device)
    cam = _front_camera()
    out = ops.raycast_mesh(verts, faces, cam)
    o, d = cam.pixel_rays(device, torch.float64)
    ref = raycast_reference(verts, faces, o, d)
    assert out.depth.dtype == torch.float64 and out.normal.dtype == torch.float64
    assert out.face_id.dtype == torch.int32 and out.mask.dtype == torch.bool
    assert out.depth.shape == (30, 40) and out.normal.shape == (30, 40, 3) and out.bary.shape == (30, 40, 2)
    assert ref["mask"].sum() > 200
    assert (out.mask != ref["mask"]).sum() <= 1  # one pixel may graze the silhouette differently
    same = out.mask & ref["mask"] & (out.face_id.long() == ref["face_id"])
    assert (out.mask & ref["mask"]).sum() - same.sum() <= 2  # edge ties
    torch.testing.assert_close(out.depth[same], ref["depth"][same], rtol=0, atol=F64_ATOL)
    torch.testing.assert_close(out.normal[same], ref["normal"][same], rtol=0, atol=F64_ATOL)
    torch.testing.assert_close(out.bary[same], ref["bary"][same], rtol=0, atol=BARY_ATOL)
    # the hit point from the barycentrics lies on the ray at the returned depth
    fa = faces[out.face_id[same].long()].long()
    b = out.bary[same]
    p = b[:, :1] * verts[fa[:, 0]] + b[:, 1:] * verts[fa[:, 1]] + (1 - b.sum(-1, keepdim=True)) * verts[fa[:, 2]]
    torch.testing.assert_close(p, o[same] + out.depth[same][:, None] * d[same], rtol=0, atol=1e-4)


def test_z_depth_of_camera_rays(device):
    """Return the camera z-depth (not the Euclidean distance) with camera rays."""
    verts, faces = _sphere(2, device=device)
    cam = _front_camera()
    out = ops.raycast_mesh(verts, faces, cam)
    o, d = cam.pixel_rays(device, torch.float64)
    p = o + out.depth[..., None] * d  # world hit points
    _, z = cam.project(p[out.mask].cpu().numpy())
    np.testing.assert_allclose(z, out.depth[out.mask].cpu().numpy(), rtol=1e-9)


def test_gradients_match_reference(device):
    """Match the reference's autograd vertex gradients of depth and normal for random upstream weights."""
    verts, faces = _sphere(2, device=device)
    cam = _front_camera()
    o, d = cam.pixel_rays(device, torch.float64)
    g = torch.Generator().manual_seed(0)
    w_depth = torch.randn(30, 40, generator=g, dtype=torch.float64).to(device)
    w_normal = torch.randn(30, 40, 3, generator=g, dtype=torch.float64).to(device)
    v1 = verts.clone().requires_grad_()
    out = ops.raycast_mesh(v1, faces, cam)
    v2 = verts.clone().requires_grad_()
    ref = raycast_reference(v2, faces, o, d)
    same = (out.mask & ref["mask"] & (out.face_id.long() == ref["face_id"])).to(torch.float64)
    assert same.sum() > 200, "gradient test must cover hit pixels"
    ((out.depth * w_depth * same).sum() + (out.normal * w_normal * same[..., None]).sum()).backward()
    ((ref["depth"] * w_depth * same).sum() + (ref["normal"] * w_normal * same[..., None]).sum()).backward()
    assert v1.grad.abs().sum() > 0
    torch.testing.assert_close(v1.grad, v2.grad, rtol=GRAD_RTOL, atol=GRAD_ATOL)


def test_repeated_backward_gives_same_gradient(device):
    """Return identical vertex gradients (CUDA: to atomics' reordering) when one render is differentiated twice."""
    verts, faces = _sphere(2, device=device)
    v = verts.clone().requires_grad_()
    out = ops.raycast_mesh(v, faces, _front_camera())
    assert out.mask.sum() > 200
    loss = out.depth.sum() + out.normal[..., 2].sum()
    g1 = torch.autograd.grad(loss, v, retain_graph=True)[0]
    g2 = torch.autograd.grad(loss, v)[0]
    assert g1.abs().sum() > 0
    if torch.device(device).type == "cuda":
        # CUDA atomics add the per-pixel contributions of a vertex in a varying order: last-bit
        # differences (observed <= 3e-14 relative in float64 on an H200); CPU reruns are exact
        torch.testing.assert_close(g1, g2, rtol=1e-12, atol=1e-12)
    else:
        torch.testing.assert_close(g1, g2, rtol=0, atol=0)


def test_mesh_query_ray_path_matches_default(device):
    """Agree between the per-ray ``wp.mesh_query_ray`` path and the default packet sweep on pixel rays."""
    verts, faces = _sphere(3, dtype=torch.float32, device=device)
    cam = _front_camera(64, 48)
    a = MeshRaycaster().raycast(verts, faces, cam)
    b = MeshRaycaster(conservative=False).raycast(verts, faces, cam)
    assert a.mask.sum() > 1000
    assert torch.equal(a.face_id, b.face_id)
    torch.testing.assert_close(a.depth, b.depth)
    torch.testing.assert_close(a.bary, b.bary, rtol=0, atol=BARY_ATOL)


def test_gradcheck_away_from_edges(device):
    """Pass torch's float64 gradcheck of depth and normal w.r.t. vertices on pixels away from edges."""
    verts, faces = _sphere(1, device=device)
    cam = _front_camera(16, 12)
    out = ops.raycast_mesh(verts, faces, cam)
    keep = out.mask & (out.bary.min(-1).values > EDGE_MARGIN) & (1 - out.bary.sum(-1) > EDGE_MARGIN)
    assert keep.sum() > 40, "gradcheck must cover hit pixels"
    face_ref = out.face_id.clone()

    def fn(v):
        r = ops.raycast_mesh(v, faces, cam)
        if not torch.equal(r.face_id[keep], face_ref[keep]):
            raise AssertionError("an FD step moved a kept pixel to another face")
        return r.depth[keep], r.normal[keep]

    v = verts.clone().requires_grad_()
    assert torch.autograd.gradcheck(fn, (v,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_analytic_plane_depth_and_gradient(device):
    """Give exact depth of a fronto-parallel plane and d depth / d z-translation = 1 at every hit."""
    verts, faces = _grid(4, z=0.0, device=device)
    verts = verts - torch.tensor([2.0, 2.0, -5.0], dtype=torch.float64, device=device)  # plane z = 5
    cam = Camera(np.array([[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]]), np.eye(4), 32, 24)
    v = verts.clone().requires_grad_()
    out = ops.raycast_mesh(v, faces, cam)
    assert out.mask.sum() == 256  # the 4 x 4 plane at depth 5 spans 16 x 16 pixels at f = 20
    torch.testing.assert_close(out.depth[out.mask], torch.full_like(out.depth[out.mask], 5.0), rtol=0, atol=1e-12)
    # winding of _grid gives normal -z in this frame or +z: either way unit and along z
    torch.testing.assert_close(out.normal[out.mask][:, 2].abs(), torch.ones_like(out.depth[out.mask]))
    out.depth.sum().backward()
    torch.testing.assert_close(v.grad[:, 2].sum(), out.mask.sum().to(torch.float64), rtol=1e-12, atol=0)
    torch.testing.assert_close(v.grad[:, :2].sum(0), torch.zeros(2, dtype=torch.float64, device=device),
                               rtol=0, atol=1e-9)


def test_float32_matches_float64(device):
    """Agree between float32 and float64 vertices on depth and normal."""
    v64, faces = _sphere(3, device=device)
    cam = _front_camera(64, 48)
    a = ops.raycast_mesh(v64.float(), faces, cam)
    b = ops.raycast_mesh(v64, faces, cam)
    assert torch.equal(a.face_id, b.face_id) and a.mask.sum() > 1000
    torch.testing.assert_close(a.depth.double(), b.depth, rtol=DEPTH_RTOL, atol=0)
    torch.testing.assert_close(a.normal.double(), b.normal, rtol=0, atol=1e-5)


def test_explicit_rays_give_ray_parameter(device):
    """Return the ray parameter t for explicit (non-unit, any-shape) rays."""
    verts, faces = _grid(2, z=0.0, device=device)
    o = torch.tensor([[[0.5, 0.25, 3.0], [1.5, 1.25, 2.0]]], dtype=torch.float64, device=device)
    d = torch.tensor([[[0.0, 0.0, -2.0], [0.0, 0.0, -0.5]]], dtype=torch.float64, device=device)
    out = ops.raycast_mesh(verts, faces, None, rays=(o, d))
    assert out.depth.shape == (1, 2) and out.mask.all()
    torch.testing.assert_close(out.depth, torch.tensor([[1.5, 4.0]], dtype=torch.float64, device=device))


def test_batch_of_cameras(device):
    """Render a list of same-size cameras as a leading batch dimension."""
    verts, faces = _sphere(2, device=device)
    cams = [_front_camera(), _front_camera(eye=(-2.0, 0.5, 2.0))]
    out = ops.raycast_mesh(verts, faces, cams)
    assert out.depth.shape == (2, 30, 40) and out.face_id.shape == (2, 30, 40)
    for i, cam in enumerate(cams):
        single = ops.raycast_mesh(verts, faces, cam)
        assert torch.equal(out.face_id[i], single.face_id)
        torch.testing.assert_close(out.depth[i], single.depth)
    with pytest.raises(ValueError, match="one image size"):
        ops.raycast_mesh(verts, faces, [cams[0], _front_camera(20, 10)])


def test_raycaster_refits_and_rebuilds(device):
    """Refit the kept BVH when only positions move and rebuild it when faces change, matching a fresh cast."""
    verts, faces = _sphere(2, dtype=torch.float32, device=device)
    cam = _front_camera()
    rc = MeshRaycaster()
    rc.raycast(verts, faces, cam)
    moved = verts * 1.1 + 0.05
    out = rc.raycast(moved, faces, cam)
    assert (rc.builds, rc.refits) == (1, 1)
    fresh = ops.raycast_mesh(moved, faces, cam)
    assert torch.equal(out.face_id, fresh.face_id)
    torch.testing.assert_close(out.depth, fresh.depth)
    flipped = faces[:, [0, 2, 1]].contiguous()
    out = rc.raycast(moved, flipped, cam)
    assert (rc.builds, rc.refits) == (2, 1)
    torch.testing.assert_close(out.normal, -fresh.normal)
    half = faces[: faces.shape[0] // 2]
    out = rc.raycast(moved, half, cam)
    assert rc.builds == 3
    assert torch.equal(out.face_id, ops.raycast_mesh(moved, half, cam).face_id)


def test_zero_faces_give_empty_outputs(device):
    """Return an all-miss render and zero gradients for a mesh with no faces, building no wp.Mesh."""
    cam = _front_camera(8, 6)
    for nv in (0, 5):
        v = torch.randn(nv, 3, dtype=torch.float64, device=device, requires_grad=True)
        rc = MeshRaycaster()
        out = rc.raycast(v, torch.zeros(0, 3, dtype=torch.int32, device=device), cam)
        assert rc._mesh is None and rc.builds == 0
        assert out.depth.shape == (6, 8) and out.normal.shape == (6, 8, 3) and out.bary.shape == (6, 8, 2)
        assert not out.mask.any() and (out.face_id == -1).all()
        assert (out.depth == 0).all() and (out.normal == 0).all()
        (out.depth.sum() + out.normal.sum()).backward()
        assert v.grad is not None and v.grad.shape == (nv, 3) and (v.grad == 0).all()
        fid, dist, cp = ops.closest_faces(v.detach(), torch.zeros(0, 3, dtype=torch.int32, device=device),
                                          torch.zeros(4, 3, dtype=torch.float64, device=device))
        assert (fid == -1).all() and torch.isinf(dist).all() and cp.shape == (4, 3)


def test_degenerate_triangles_never_hit(device):
    """Never hit zero-area triangles (collinear, repeated vertex) and keep outputs and gradients finite."""
    verts, faces = _grid(2, z=0.0, device=device)
    extra_v = torch.tensor([[0.2, 0.2, 1.0], [0.8, 0.8, 1.0], [1.4, 1.4, 1.0], [1.0, 0.5, 1.0]],
                           dtype=torch.float64, device=device)
    nv = verts.shape[0]
    extra_f = torch.tensor([[nv, nv + 1, nv + 2], [nv + 3, nv + 3, nv + 1], [nv + 3, nv + 3, nv + 3]],
                           dtype=torch.int32, device=device)
    v = torch.cat([verts, extra_v]).requires_grad_()
    f = torch.cat([faces, extra_f])
    # rays straight down through the degenerate triangles' vertices and edges
    xy = torch.tensor([[0.2, 0.2], [0.5, 0.5], [0.8, 0.8], [1.0, 0.5], [1.4, 1.4], [0.9, 0.65]],
                      dtype=torch.float64, device=device)
    o = torch.cat([xy, torch.full_like(xy[:, :1], 3.0)], 1)
    d = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64, device=device).expand_as(o).contiguous()
    out = ops.raycast_mesh(v, f, None, rays=(o, d))
    assert out.mask.all() and (out.face_id < faces.shape[0]).all(), "rays must pass degenerate faces to the grid"
    torch.testing.assert_close(out.depth, torch.full_like(out.depth, 3.0))
    (out.depth.sum() + out.normal.sum()).backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0
    assert (v.grad[nv:] == 0).all()


def test_rays_through_vertices_and_edges_hit(device):
    """Hit a flat grid exactly once (no holes) with rays through its vertices and along its shared edges."""
    verts, faces = _grid(6, z=0.0, device=device)
    # every vertex, every edge midpoint (axis and diagonal edges), straight and oblique rays
    g = torch.arange(0, 6.01, 0.5, dtype=torch.float64, device=device)
    xx, yy = torch.meshgrid(g[1:-1], g[1:-1], indexing="ij")
    target = torch.stack([xx.ravel(), yy.ravel(), torch.zeros_like(xx.ravel())], 1)
    for direction in ([0.0, 0.0, -1.0], [0.3, -0.2, -1.0], [1.0, 1.0, -0.5]):
        dvec = torch.tensor(direction, dtype=torch.float64, device=device).expand_as(target).contiguous()
        o = target - 2.0 * dvec
        out = ops.raycast_mesh(verts, faces, None, rays=(o, dvec))
        assert out.mask.all(), f"{int((~out.mask).sum())} rays slipped through the grid along {direction}"
        torch.testing.assert_close(out.depth, torch.full_like(out.depth, 2.0), rtol=1e-6, atol=0)
        # exactly one hit: the returned face contains the target point (vertex or shared edge)
        fa = faces[out.face_id.long()].long()
        lo, hi = verts[fa].min(1).values, verts[fa].max(1).values
        assert ((target >= lo - 1e-9) & (target <= hi + 1e-9)).all()


@pytest.mark.parametrize("subdivisions", [2, 4])
def test_closed_mesh_vertex_rays_do_not_leak(device, subdivisions):
    """Hit a closed mesh exactly at its vertices from inside (every ray) and outside (never beyond)."""
    verts, faces = _sphere(subdivisions, dtype=torch.float32, device=device)
    vn = torch.tensor(trimesh.Trimesh(verts.cpu().numpy(), faces.cpu().numpy(), process=False).vertex_normals,
                      dtype=torch.float32, device=device)
    rc = MeshRaycaster()
    for eye, inside in (((0.0, 0.0, 0.0), True), ((0.1, 0.2, 0.3), True), ((0.0, 0.0, 4.0), False),
                        ((3.0, 1.0, 0.5), False)):
        o = torch.tensor(eye, dtype=torch.float32, device=device).expand_as(verts).contiguous()
        d = verts - o
        out = rc.raycast(verts, faces, None, rays=(o, d))
        # rays grazing a silhouette vertex may pass it (exact arithmetic on the float32 ray decides)
        facing = ((vn * d).sum(1) / d.norm(dim=1)).abs() > SILHOUETTE_COS
        check = torch.ones_like(facing) if inside else facing
        assert check.sum() > 0.3 * len(verts)
        assert out.mask[check].all(), f"{int((~out.mask[check]).sum())} vertex rays slipped through the mesh"
        # the aimed-at vertex lies on the mesh at t = 1: a first hit beyond it is a leak
        assert (out.depth[check] <= 1.0 + 1e-6).all(), "a vertex ray passed through the surface"


def test_parallel_rays_and_rays_on_bounding_box_faces(device):
    """Miss triangles parallel to the ray without NaN and hit boxes from origins on their bounding-box faces."""
    verts, faces = _grid(3, z=0.0, device=device)
    o = torch.tensor([[-1.0, 0.5, 0.0], [0.5, -1.0, 0.0], [-1.0, 1.0, 0.0]], dtype=torch.float64, device=device)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64, device=device)
    v = verts.clone().requires_grad_()
    out = ops.raycast_mesh(v, faces, None, rays=(o, d))  # rays inside the grid's plane
    assert torch.isfinite(out.depth).all() and torch.isfinite(out.normal).all()
    assert not out.mask.any()
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    bv = torch.tensor(box.vertices, dtype=torch.float64, device=device)
    bf = torch.tensor(box.faces, dtype=torch.int32, device=device)
    # origins on the box's (and its AABB's) faces, axis-aligned directions with zero components
    o = torch.tensor([[-1.0, 0.3, 0.2], [0.3, 1.0, -0.4], [0.1, 0.2, 3.0], [-1.0, 1.0, 0.5]],
                     dtype=torch.float64, device=device)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]],
                     dtype=torch.float64, device=device)
    out = ops.raycast_mesh(bv, bf, None, rays=(o, d))
    assert out.mask.all()
    torch.testing.assert_close(out.depth, torch.tensor([0.0, 0.0, 2.0, 0.0], dtype=torch.float64, device=device),
                               rtol=0, atol=1e-6)


def test_camera_inside_closed_mesh_sees_back_faces(device):
    """Hit the surrounding back faces from a camera inside a closed mesh, normals pointing away."""
    verts, faces = _sphere(3, device=device)
    cam = Camera.look_at([0.05, -0.02, 0.1], [1, 0.2, 0.3], [0, 0, 1], fov_x=1.2, width=32, height=24)
    out = ops.raycast_mesh(verts, faces, cam)
    o, d = cam.pixel_rays(device, torch.float64)
    assert out.mask.all()
    assert (out.depth > 0).all()
    assert ((out.normal * d).sum(-1) > 0).all(), "outward normals of back faces point away from the camera"


def test_large_mesh_build_and_cast():
    """Build a BVH over 10^6 faces and cast a view against it within a bounded time."""
    n = 708  # 2 * 708^2 = 1,002,528 faces
    verts, faces = _grid(n, z=0.0, dtype=torch.float32)
    verts = verts / n
    verts[:, 2] = 0.05 * torch.sin(20 * verts[:, 0]) * torch.cos(15 * verts[:, 1])
    assert faces.shape[0] > 1_000_000
    cam = Camera.look_at([0.5, 0.5, 1.5], [0.5, 0.5, 0.0], [0, 1, 0], fov_x=0.5, width=128, height=128)
    rc = MeshRaycaster()
    t0 = time.perf_counter()
    out = rc.raycast(verts, faces, cam)
    elapsed = time.perf_counter() - t0
    assert out.mask.all()
    z = out.depth
    assert torch.isfinite(z).all() and (z > 1.3).all() and (z < 1.6).all()
    assert elapsed < 30.0, f"10^6-face build and cast took {elapsed:.1f} s"  # ~1 s measured; busy-CI margin
    t0 = time.perf_counter()
    rc.raycast(verts * 1.01, faces, cam)
    assert rc.refits == 1 and time.perf_counter() - t0 < elapsed


def test_closest_faces_match_reference(device):
    """Agree with the brute-force reference on nearest face ids, distances and closest points."""
    verts, faces = _sphere(2, device=device)
    g = torch.Generator().manual_seed(1)
    pts = (torch.rand(300, 3, generator=g, dtype=torch.float64) * 3 - 1.5).to(device)
    fid, dist, cp = ops.closest_faces(verts, faces, pts)
    assert fid.dtype == torch.int32 and dist.dtype == torch.float64 and cp.shape == (300, 3)
    fid_ref, dist_ref, cp_ref = closest_point_reference(verts.cpu().numpy(), faces.cpu().numpy(), pts.cpu().numpy())
    np.testing.assert_allclose(dist.cpu().numpy(), dist_ref, rtol=0, atol=CLOSEST_ATOL)
    np.testing.assert_allclose(cp.cpu().numpy(), cp_ref, rtol=0, atol=CLOSEST_ATOL)
    # ties (closest point on a shared edge or vertex) may pick another face: it must be as close
    assert (fid.cpu().numpy() == fid_ref).mean() > 0.5
    fv = faces[fid.long()].cpu().numpy()
    for i in np.nonzero(fid.cpu().numpy() != fid_ref)[0]:
        _, d_i, _ = closest_point_reference(verts.cpu().numpy(), fv[i:i + 1], pts[i:i + 1].cpu().numpy())
        np.testing.assert_allclose(d_i, dist_ref[i:i + 1], rtol=0, atol=CLOSEST_ATOL)
    far = torch.tensor([[10.0, 0, 0]], dtype=torch.float64, device=device)
    fid, dist, _ = ops.closest_faces(verts, faces, far, max_distance=1.0)
    assert fid.item() == -1 and torch.isinf(dist).all()
    fid, dist, _ = ops.closest_faces(verts, faces, far, max_distance=20.0)
    assert fid.item() >= 0 and 8.5 < dist.item() < 9.5
    rc = MeshRaycaster()
    fid2, dist2, _ = rc.closest_faces(verts, faces, pts)
    assert torch.equal(fid2, ops.closest_faces(verts, faces, pts)[0])


def test_validation_errors(device):
    """Raise TypeError/ValueError naming the argument before any launch."""
    verts, faces = _sphere(1, device=device)
    cam = _front_camera(8, 6)
    with pytest.raises(ValueError, match="verts"):
        ops.raycast_mesh(verts[:, :2], faces, cam)
    with pytest.raises(TypeError, match="faces"):
        ops.raycast_mesh(verts, faces.float(), cam)
    with pytest.raises(ValueError, match="faces"):
        ops.raycast_mesh(verts, faces + 1000, cam)
    bad = verts.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="verts must be finite"):
        ops.raycast_mesh(bad, faces, cam)
    with pytest.raises(TypeError, match="camera"):
        ops.raycast_mesh(verts, faces, "cam")
    with pytest.raises(TypeError, match="camera or rays"):
        ops.raycast_mesh(verts, faces, None)
    o = torch.zeros(5, 3, dtype=torch.float64, device=device)
    with pytest.raises(ValueError, match="rays"):
        ops.raycast_mesh(verts, faces, None, rays=(o, o[:4]))
    with pytest.raises(ValueError, match="max_distance"):
        ops.closest_faces(verts, faces, o, max_distance=-1.0)
    with pytest.raises(ValueError, match="bvh_constructor"):
        MeshRaycaster(bvh_constructor="octree")
    assert ops.raycast_mesh(verts, faces.long(), cam).mask.any()  # int64 faces accepted


def test_ray_list_in_random_order_matches_the_reference(device):
    """A 1-D ray list is swept in packets of four in a coherent order (Morton order of origin, then
    direction): every ray in exactly one packet, a packet's rays from one origin, and rays from several
    origins towards random targets, given in random order, each get the brute-force reference's hit and
    depth, misses included (a packet of four unrelated rays would sweep most of the BVH: the order is
    for speed, never a change of result)."""
    from wtopo.raycast import _list_packets

    verts, faces = _sphere(2, dtype=torch.float64, device=device)
    g = torch.Generator().manual_seed(0)
    origins = (torch.randn(6, 3, generator=g, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, 3.0],
                                                                                        dtype=torch.float64))
    o = origins.repeat_interleave(300, dim=0)
    d = torch.rand(len(o), 3, generator=g, dtype=torch.float64) * 3.0 - 1.5 - o  # towards targets in a box
    perm = torch.randperm(len(o), generator=g)
    which = torch.arange(6).repeat_interleave(300)[perm]  # each ray's origin
    o, d = o[perm].to(device), d[perm].to(device)
    packets = _list_packets(o.float(), d.float()).cpu().long()
    assert packets.shape == (len(o) // 4, 4) and torch.equal(packets.flatten().sort().values, torch.arange(len(o)))
    one_origin = (which[packets] == which[packets[:, :1]]).all(dim=1).float().mean()
    assert one_origin > 0.95  # in the given order about 6**-3 of the packets would be
    out = ops.raycast_mesh(verts, faces, None, rays=(o, d))
    ref = raycast_reference(verts.cpu(), faces.cpu(), o.cpu(), d.cpu())
    assert 0.2 * len(o) < int(ref["mask"].sum()) < 0.9 * len(o)  # hits and misses both exercised
    assert torch.equal(out.mask.cpu(), ref["mask"])
    assert torch.equal(out.face_id.cpu().long(), ref["face_id"])
    torch.testing.assert_close(out.depth.cpu()[ref["mask"]], ref["depth"][ref["mask"]], rtol=DEPTH_RTOL, atol=0)
