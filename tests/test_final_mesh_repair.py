# SPDX-License-Identifier: Apache-2.0
"""The final mesh's repair: Poisson re-meshing of open meshes, hole filling, closed marching cubes, and the
components an object's final mesh and its TSDF re-initialisation keep after the repair."""

import numpy as np
import pytest
import trimesh
from mesh_scenes import depths_of, ring_cameras


def _open_sphere(subdivisions=3):
    """An icosphere with a cap cut away: not watertight, so the final policy re-meshes it."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.3)
    s.apply_translation([0.5, 0.5, 0.5])
    keep = s.triangles_center[:, 2] < 0.7
    return trimesh.Trimesh(s.vertices, s.faces[keep], process=True)


def _remesh_config():
    from wtopo.fitting import FitConfig

    cfg = FitConfig()
    cfg.final.resolution = 48
    return cfg


def test_poisson_remesh_closes_an_open_mesh_and_records_its_device():
    from wtopo.fitting._final_mesh import poisson_remesh

    events = []
    src = _open_sphere()
    assert not src.is_watertight
    out = poisson_remesh(src, _remesh_config(), record=lambda e, **k: events.append((e, k)))
    assert out.is_watertight and len(out.faces) > 500
    off = np.abs(np.linalg.norm(out.vertices - 0.5, axis=1) - 0.3)
    below = out.vertices[:, 2] < 0.65  # where the open mesh is; above it Poisson closes the cut cap
    assert below.sum() > 100 and off[below].max() < 0.03 and out.vertices[:, 2].max() > 0.68
    assert events == [("poisson_remesh", {"watertight": True, "device": "cpu"})]
    # where the open mesh is, the re-mesh's vertices lie on it (moved onto its faces), not on Poisson's
    # smoothed copy of it; the closing cap stays Poisson's
    from wtopo.metrics._surface import _Surface

    on_src = _Surface("src", src, 0, 0).closest(out.vertices[below])[0]
    assert on_src.max() < 1e-5, on_src.max()


def test_fill_boundary_loops_caps_small_simple_holes_consistently_and_leaves_large_or_pinched_ones():
    from wtopo.fitting.tsdf import fill_boundary_loops

    box = trimesh.creation.box()
    box.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(box.vertices), 1))
    box.update_faces(np.arange(len(box.faces)) != 0)  # one triangle gone: a three-edge loop
    assert not box.is_watertight
    assert fill_boundary_loops(box, 48) == 1  # one triangle, no new vertex
    assert box.is_watertight and box.is_winding_consistent and np.isclose(box.volume, 1.0)
    assert len(box.visual.vertex_colors) == len(box.vertices) == 8 and len(box.faces) == 12

    ball = trimesh.creation.icosphere(subdivisions=2)
    ball.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(ball.vertices), 1))
    ring = np.flatnonzero((ball.faces == 0).any(axis=1))  # the faces round vertex 0: a loop of 5 edges
    ball = trimesh.Trimesh(ball.vertices, np.delete(ball.faces, ring, axis=0), vertex_colors=ball.visual.vertex_colors,
                           process=False)
    nv = len(ball.vertices)
    assert fill_boundary_loops(ball, 48) == 1  # a fan round a new centre vertex, coloured as the loop
    assert ball.is_watertight and ball.is_winding_consistent and ball.volume > 0 and len(ball.vertices) == nv + 1
    assert (ball.visual.vertex_colors[-1] == [200, 100, 50, 255]).all()

    sphere = trimesh.creation.icosphere(subdivisions=3)
    cut = sphere.triangles_center[:, 2] < 0.5  # a cap of a loop of more than 8 edges
    big = trimesh.Trimesh(sphere.vertices, sphere.faces[cut], process=True)
    n_loop = len(big.outline().entities[0].points) - 1
    assert n_loop > 8 and fill_boundary_loops(big, 8) == 0 and not big.is_watertight
    assert fill_boundary_loops(big, n_loop) == 1 and big.is_watertight and big.is_winding_consistent
    assert big.volume > 0

    # two holes that share a vertex: their boundary passes that vertex twice, no simple loop to cap
    s = trimesh.creation.icosphere(subdivisions=2)
    v = 0
    ring = np.flatnonzero((s.faces == v).any(axis=1))
    pinched = trimesh.Trimesh(s.vertices, np.delete(s.faces, ring[[0, 3]], axis=0), process=False)
    assert not pinched.is_watertight
    assert fill_boundary_loops(pinched, 48) == 0 and not pinched.is_watertight


def test_poisson_remesh_falls_back_to_the_cpu_when_its_device_runs_out_of_memory(monkeypatch):
    """The solve runs on the fit's device; an allocation failure there re-runs it on the CPU with a warning
    (``meta`` stands in for a GPU: this machine may have none). Other errors, and the CPU's own, propagate."""
    import torch

    import wtopo.fitting._final_mesh as stages

    real, seen = stages.poisson_mesh, []

    def on_device(points, *a, **k):
        seen.append(points.device.type)
        if points.device.type != "cpu":
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 3.38 GiB")
        return real(points, *a, **k)

    monkeypatch.setattr(stages, "poisson_mesh", on_device)
    recovered = []  # Warp's sort on the failed device is put back in order (wtopo._bridge.recover_after_oom)
    monkeypatch.setattr(stages._bridge, "recover_after_oom", recovered.append)
    events = []
    with pytest.warns(RuntimeWarning, match="ran out of memory on meta; re-meshing on the CPU"):
        out = stages.poisson_remesh(_open_sphere(), _remesh_config(), record=lambda e, **k: events.append(k),
                                    device="meta")
    assert seen == ["meta", "cpu"] and out.is_watertight and events[-1]["device"] == "cpu"
    assert recovered == []  # only a CUDA device's failure needs it (meta is not one)

    def warp_failure(points, *a, **k):
        raise RuntimeError("Failed to allocate 3623878656 bytes on device 'cuda:0'")

    monkeypatch.setattr(stages, "poisson_mesh", warp_failure)
    with pytest.raises(RuntimeError, match="Failed to allocate"):  # the CPU's own failure is the user's to see
        stages.poisson_remesh(_open_sphere(), _remesh_config(), record=lambda e, **k: None, device="cpu")

    def broken(points, *a, **k):
        raise RuntimeError("a kernel bug, not memory")

    monkeypatch.setattr(stages, "poisson_mesh", broken)
    with pytest.raises(RuntimeError, match="kernel bug"):
        stages.poisson_remesh(_open_sphere(), _remesh_config(), record=lambda e, **k: None, device="meta")


def test_a_marching_cubes_mesh_stays_closed_when_float32_puts_edge_vertices_on_grid_nodes():
    """Nodes a hair outside the surface put their crossing edges' vertices within float32 rounding of the
    node (as 768^3 grids do at random): merged by position they collapse faces into non-manifold edges and
    the mesh opens; ``cleanup_mesh(weld=False)`` keeps marching cubes' own vertex sharing and stays closed."""
    import torch

    from wtopo.fitting.tsdf import cleanup_mesh
    from wtopo.marching_cubes import marching_cubes

    n = 24
    g = (np.arange(n) + 0.5) / n
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    f = np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2) - 0.3
    near = (f > 0) & (f < 0.5 / n)
    f[near] = 1e-9  # t of their crossing edges ~1e-7 cells: the vertex rounds onto the node
    v, fa = marching_cubes(torch.as_tensor(f, dtype=torch.float32), 0.0)
    raw = trimesh.Trimesh(v.numpy().astype(np.float64), fa.numpy(), process=False)
    assert near.sum() > 100 and raw.is_watertight
    welded = cleanup_mesh(raw, repair=False)
    assert not welded.is_watertight, "the case must reproduce the collapse"
    kept = cleanup_mesh(raw, repair=False, weld=False)
    assert kept.is_watertight and kept.is_winding_consistent and len(kept.faces) == len(raw.faces)


def test_an_objects_final_mesh_is_repaired_after_the_unsupported_components_go(monkeypatch):
    """The repair (hole filling, face orientation) works component by component, so it runs on what the
    support rule keeps: a 512-px fit's TSDF mesh has 20,000-30,000 specks, and repairing them first kept the
    fit on one CPU core for minutes. The kept mesh is the same as before: specks dropped, the object closed."""
    import types

    import torch

    import wtopo.fitting._final_mesh as stages
    from wtopo.fitting import FitConfig

    seen = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    cams = ring_cameras()
    depths = depths_of(seen, cams)
    rng = np.random.default_rng(0)
    specks = []
    for _ in range(40):  # unseen specks, as the TSDF leaves around a sparse capture
        s = trimesh.creation.icosphere(subdivisions=0, radius=0.02)
        s.apply_translation(rng.uniform(-1.5, 1.5, 3) + np.array([0, 0, 2.0]))
        specks.append(s)
    fused = trimesh.util.concatenate([seen, *specks])
    flipped = fused.faces.copy()
    flipped[: len(seen.faces) // 2] = flipped[: len(seen.faces) // 2, ::-1]  # half the object wound inwards
    fused = trimesh.Trimesh(fused.vertices, flipped, process=False)

    monkeypatch.setattr(stages, "render_depths", lambda *a, **k: (depths, [np.zeros((*d.shape, 3)) for d in depths]))
    monkeypatch.setattr(stages, "auto_bounds", lambda *a, **k: types.SimpleNamespace(to_dict=lambda: {}))
    monkeypatch.setattr(stages, "fuse_depths", lambda *a, **k: fused)
    real, repaired = stages.repair_mesh, []

    def counting(mesh):
        repaired.append(len(mesh.split(only_watertight=False)))
        return real(mesh)

    monkeypatch.setattr(stages, "repair_mesh", counting)
    events = []
    surfels = types.SimpleNamespace(means=torch.zeros(1, 3), opacities=torch.ones(1))
    out = stages.final_mesh(surfels, cams, FitConfig(), render=None, proxy=None, guided=True, tsdf_info={},
                            record=lambda e, **k: events.append((e, k)))
    assert repaired and repaired[0] == 1  # the object alone: the 40 specks were dropped before the repair
    policy = dict(events)["mesh_policy"]
    assert policy["components"]["components"] == 41 and policy["components"]["kept"] == 1
    assert out.is_watertight and out.is_winding_consistent and out.volume > 0
    np.testing.assert_allclose(out.area, seen.area, rtol=1e-9)


def test_an_objects_poisson_remesh_keeps_only_the_components_the_views_support(monkeypatch):
    """The watertight re-mesh can wrap inner sheets of the fused mesh into closed pockets of their own
    (a ten-view cup at 768^3 came back in 137-343 components). They go by the same support rule as the
    fused mesh's components: pockets inside the object, which no rendered depth reaches, are dropped;
    a small part the views see stays; the mesh stays closed."""
    import types

    import torch

    import wtopo.fitting._final_mesh as stages
    from wtopo.fitting import FitConfig

    body = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    knob = trimesh.creation.icosphere(subdivisions=2, radius=0.12)  # a separate part the views see
    knob.apply_translation([0.0, 0.0, 0.8])
    cams = ring_cameras()
    depths = depths_of(trimesh.util.concatenate([body, knob]), cams)
    pockets = []
    for c in ([0.1, 0.0, 0.0], [-0.15, 0.1, 0.05], [0.0, -0.2, -0.1]):  # inside the body: no view reaches them
        p = trimesh.creation.icosphere(subdivisions=1, radius=0.06)
        p.apply_translation(c)
        pockets.append(p)
    remeshed = trimesh.util.concatenate([body, knob, *pockets])
    opened = trimesh.Trimesh(body.vertices, body.faces[:-4], process=False)  # the fused mesh: not closed
    assert not opened.is_watertight

    monkeypatch.setattr(stages, "render_depths", lambda *a, **k: (depths, [np.zeros((*d.shape, 3)) for d in depths]))
    monkeypatch.setattr(stages, "auto_bounds", lambda *a, **k: types.SimpleNamespace(to_dict=lambda: {}))
    monkeypatch.setattr(stages, "fuse_depths", lambda *a, **k: opened)
    monkeypatch.setattr(stages, "repair_mesh", lambda m: m)  # left open, so the re-mesh runs
    calls = []

    def remesh(mesh, cfg, *, record, device="cpu"):
        calls.append(len(mesh.faces))
        return remeshed

    monkeypatch.setattr(stages, "poisson_remesh", remesh)
    events = []
    surfels = types.SimpleNamespace(means=torch.zeros(1, 3), opacities=torch.ones(1))
    out = stages.final_mesh(surfels, cams, FitConfig(), render=None, proxy=None, guided=True, tsdf_info={},
                            record=lambda e, **k: events.append((e, k)))
    assert calls == [len(opened.faces)]  # the re-mesh ran on the open fused mesh
    policy = dict(events)["mesh_policy"]
    assert policy["remesh_components"]["components"] == 5 and policy["remesh_components"]["kept"] == 2
    assert all(d["views"] < 3 for d in policy["remesh_components"]["dropped"])
    assert out.is_watertight and len(out.split(only_watertight=False)) == 2
    np.testing.assert_allclose(out.area, body.area + knob.area, rtol=1e-9)


def test_the_tsdf_reinit_of_an_object_keeps_every_component_the_views_support(monkeypatch):
    """The re-initialisation's fused mesh keeps its components by view support, as the final mesh does, not
    the largest alone: a torus beside a capsule (fewer faces) both get surfels, an unseen speck gets none.
    Keeping only the largest component lost the capsule of the ring_capsule benchmark for the rest of the fit
    (no surfel left on it: Chamfer 4.7 % against the bunny's 0.24 %)."""
    import types

    import torch

    import wtopo.fitting._reinit as reinit
    from wtopo.fitting import FitConfig

    torus = trimesh.creation.torus(0.6, 0.2, major_sections=64, minor_sections=32)  # 4096 faces: the largest
    torus.apply_translation([-0.7, 0, 0])
    capsule = trimesh.creation.capsule(height=0.6, radius=0.2, count=[16, 16])  # 512 faces
    capsule.apply_translation([0.8, 0, 0])
    assert len(torus.faces) > len(capsule.faces)
    seen = trimesh.util.concatenate([torus, capsule])
    cams = ring_cameras()
    depths = depths_of(seen, cams)  # the speck is not in the rendered depth: no view supports it
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    speck.apply_translation([0, 0, 1.2])
    fused = trimesh.util.concatenate([seen, speck])

    monkeypatch.setattr(reinit, "render_depths", lambda *a, **k: (depths, [np.zeros((*d.shape, 3)) for d in depths]))
    monkeypatch.setattr(reinit, "auto_bounds", lambda *a, **k: types.SimpleNamespace(to_dict=lambda: {}))
    monkeypatch.setattr(reinit, "fuse_depths", lambda *a, **k: fused)
    cfg = FitConfig()
    cfg.tsdf.max_faces = 100_000  # one surfel per face, no decimation
    surfels = types.SimpleNamespace(means=torch.zeros(1, 3), opacities=torch.ones(1), sh_degree=0)
    events = []
    out = reinit.tsdf_reinit(surfels, cams, cfg, render=None, background_rule=False,
                             record=lambda e, **k: events.append((e, k)))
    means = out.surfels.means.detach().numpy()
    assert len(means) == len(seen.faces)
    near_capsule = np.linalg.norm(means - [0.8, 0, 0], axis=1) < 0.6
    assert near_capsule.sum() == len(capsule.faces) and (means[:, 2] < 1.0).all()  # the capsule's; no speck's
    info = dict(events)["tsdf_reinit"]
    assert info["components"]["components"] == 3 and info["components"]["kept"] == 2
