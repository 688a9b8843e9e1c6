# SPDX-License-Identifier: Apache-2.0
"""Chunked fitting: partition, camera assignment, merge without seams, the engine on one and two processes."""

import json
import os

import numpy as np
import pytest
import torch
import trimesh
from fit_configs import small_fit_config
from shapes import sphere_lattice

from wtopo import chunks as wc
from wtopo import metrics
from wtopo.chunks.partition import _grid_chunks
from wtopo.chunks.synthetic import street_cameras
from wtopo.fitting import fit
from wtopo.io.ply import SurfelArrays
from wtopo.scene import Scene

# The 2-chunk fit against the single fit of the same tiny scene (2 objects, 16 views of 40 x 30 px,
# 20 warm-up iterations): F1 against the truth at tau = 1 % of the ROI diagonal. Measured on this
# project's 2-core CPU: single 0.24, 2 chunks 0.34 (each chunk gets the whole proxy / TSDF grid,
# so it is finer); the chunked fit may not be worse than the single fit by more than this.
F1_TOLERANCE = 0.05
# Symmetric Chamfer between the two meshes, fraction of the ROI diagonal: measured 1.4-1.7 %; both fits
# are coarse (a voxel of the single fit's 48^3 final grid is 1.3 % of the ROI's longest side).
CHAMFER_TOLERANCE = 0.03
TAU_FRACTION = 0.01


def _tiny_config(warmup=20):
    return small_fit_config(warmup, 0, points=300, grids=(32, 48, 32), max_faces=800, density_every=10, eval_every=0)


def _camera_scene(n_objects=3, orbit=6, forward=6):
    """The street rig's cameras over blank images (enough for planning: no rendering)."""
    cams = street_cameras(n_objects, orbit, forward, (32, 24))
    lo, hi = np.array([-2.5, -1.5, -0.1]), np.array([4.5 * (n_objects - 1) + 2.5, 1.5, 2.2])
    return Scene(cams, np.zeros((len(cams), 24, 32, 3), np.float32), bounds=(lo, hi))


def _plan(lo, hi, grid, overlap=0.15) -> wc.ChunkPlan:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return wc.ChunkPlan(lo, hi, grid, _grid_chunks(lo, hi, grid, overlap), "test", True)


def test_chunk_grid_cuts_the_longest_axes():
    """Cut the longest axis first and keep cutting whichever cells are longest."""
    assert wc.chunk_grid((10.0, 3.0, 2.0), 2) == (2, 1, 1)
    assert wc.chunk_grid((4.0, 4.0, 1.0), 4) == (2, 2, 1)
    assert wc.chunk_grid((9.0, 3.0, 1.0), 3) == (3, 1, 1)
    with pytest.raises(ValueError, match="extent"):
        wc.chunk_grid((1.0, 0.0, 1.0), 2)


def test_partition_covers_the_roi_and_cores_are_disjoint():
    """Give every point of the ROI (and beyond) exactly one core; boxes hold their cores and stay in the ROI."""
    plan = _plan([-1, 0, 0], [5, 2, 1], (3, 2, 1))
    rng = np.random.default_rng(0)
    pts = rng.uniform([-3, -1, -1], [7, 3, 2], (5000, 3))
    inside = np.stack([np.all((pts >= np.where(np.isinf(c.core_lower), -np.inf, c.core_lower))
                              & (pts < c.core_upper), axis=1) for c in plan.chunks])
    np.testing.assert_array_equal(inside.sum(axis=0), 1)  # half-open cores: one owner each
    np.testing.assert_array_equal(np.argmax(inside, axis=0), wc.core_owner(pts, plan))
    for c in plan.chunks:
        core_lo, core_hi = np.maximum(c.core_lower, plan.roi_lower), np.minimum(c.core_upper, plan.roi_upper)
        assert np.all(c.lower <= core_lo) and np.all(c.upper >= core_hi)
        assert np.all(c.lower >= plan.roi_lower) and np.all(c.upper <= plan.roi_upper)
    assert plan.cuts() == [(0, 1.0), (0, 3.0), (1, 1.0)]


def test_plan_decides_the_count_and_records_why():
    """Take the configured count when given; else at least one chunk per process, with the reason."""
    scene = _camera_scene()
    p = wc.plan_chunks(scene, wc.ChunkConfig(chunks=3))
    assert p.grid == (3, 1, 1) and p.overridden and "ChunkConfig.chunks" in p.reason
    auto = wc.plan_chunks(scene, wc.ChunkConfig(), world_size=2)
    assert len(auto.chunks) >= 2 and not auto.overridden and "for one per process" in auto.reason
    assert wc.plan_chunks(scene, wc.ChunkConfig(chunks=1)).chunks[0].cameras == list(range(len(scene)))
    few = wc.plan_chunks(scene, wc.ChunkConfig(max_views=10))
    assert len(few.chunks) >= 3 and "at most 10 a chunk" in few.reason
    with pytest.raises(ValueError, match="ChunkConfig.overlap"):
        wc.plan_chunks(scene, wc.ChunkConfig(overlap=0.7))
    with pytest.raises(ValueError, match="world_size"):
        wc.plan_chunks(scene, wc.ChunkConfig(), world_size=0)


def test_cameras_go_to_the_chunks_they_see():
    """Give each object's orbit ring to that object's chunk; a camera looking away from a chunk does not get it."""
    scene = _camera_scene(n_objects=3, orbit=6, forward=6)
    plan = wc.plan_chunks(scene, wc.ChunkConfig(chunks=3))
    for k in range(3):
        ring = set(range(6 * k, 6 * k + 6))
        assert ring <= set(plan.chunks[k].cameras), (k, plan.chunks[k].cameras)
    # ring 0's camera 0 looks along -x, away from chunk 2; ring 2's camera 3 looks along +x, away from
    # chunk 0 (occlusion is not tested: ring 0's camera 3 looks along the row and gets every chunk)
    assert 0 not in plan.chunks[2].cameras and 15 not in plan.chunks[0].cameras
    forward = set(range(18, 24))
    assert all(set(c.cameras) & forward for c in plan.chunks)  # the drive-by line films every chunk


def _split_sphere(jitter: float):
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    plan = _plan([-1.2, -1.2, -1.2], [1.2, 1.2, 1.2], (2, 1, 1))
    rng = np.random.default_rng(1)
    meshes = {}
    for i in range(2):  # each chunk has its own copy of the vertices, moved a little along the cut plane
        v = np.asarray(sphere.vertices) + rng.uniform(-jitter, jitter, sphere.vertices.shape) * [0, 1, 1]
        meshes[i] = trimesh.Trimesh(v, sphere.faces, process=False)
    return sphere, plan, meshes


# exact copies, and copies that differ by up to 1/10 of an edge (0.14-0.16) along the cut plane (moving
# vertices across it would move face centroids across and give a face to both cores or to neither)
@pytest.mark.parametrize("jitter", [0.0, 0.01])
def test_merge_of_two_halves_has_no_seam(jitter):
    """Weld the two cores of a split sphere back into one closed surface with the original edges."""
    sphere, plan, meshes = _split_sphere(jitter)
    merged, info = wc.merge_meshes(meshes, plan)
    assert len(merged.faces) == len(sphere.faces)
    assert len(merged.edges_unique) == len(sphere.edges_unique)
    assert merged.is_watertight and info["open_edges_near_cuts_after"] == 0
    assert info["open_edges_near_cuts_before"] > 0 and info["welded"] > 0
    assert sum(info["faces_per_chunk"].values()) == len(sphere.faces)


def test_merge_leaves_a_crack_wider_than_the_tolerance_open():
    """Keep a seam open (and count it) where the two chunks disagree by more than the weld tolerance."""
    sphere, plan, meshes = _split_sphere(0.0)
    meshes[1] = trimesh.Trimesh(np.asarray(sphere.vertices) + [0.0, 0.0, 0.3], sphere.faces, process=False)
    merged, info = wc.merge_meshes(meshes, plan)
    assert not merged.is_watertight and info["open_edges_near_cuts_after"] > 0


def test_merge_surfels_keeps_each_core_once():
    """Keep each chunk's surfels in its core: two identical chunk copies give back the original set."""
    plan = _plan([0, 0, 0], [2, 1, 1], (2, 1, 1))
    rng = np.random.default_rng(2)
    n = 200
    s = SurfelArrays(means=rng.uniform(-1, 3, (n, 3)).astype(np.float32),
                     quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), scales=np.full((n, 2), 0.01, np.float32),
                     opacities=np.full(n, 0.5, np.float32), sh=rng.uniform(0, 1, (n, 1, 3)).astype(np.float32))
    means, quats, scales, opac, sh = wc.merge_surfels({0: s, 1: s}, plan)
    assert len(means) == n and sh.shape == (n, 1, 3)
    np.testing.assert_array_equal(np.sort(means[:, 0]), np.sort(s.means[:, 0]))


def test_rank_assignment_splits_the_chunks():
    """Give rank r the chunks i % world == r: disjoint, and together all of them."""
    got = [wc.rank_chunks(5, r, 2) for r in range(2)]
    assert got == [[0, 2, 4], [1, 3]]
    with pytest.raises(ValueError, match="rank"):
        wc.rank_chunks(5, 2, 2)


@pytest.fixture(scope="module")
def street():
    """Two objects in a row on the environment's ground, 12 orbit + 4 forward views of 40 x 30 px, 2000 points."""
    return wc.street_scene(2, orbit_views=6, forward_views=4, resolution=(40, 30), points=2000)


@pytest.mark.slow
def test_two_chunk_fit_matches_the_single_fit(street, tmp_path):
    """Fit the scene whole and as 2 chunks: the merged mesh is as good against the truth and close to the whole fit."""
    cfg = _tiny_config()
    single = fit(street, cfg, progress=False)
    res = wc.fit_chunked(street, tmp_path, cfg, chunk_config=wc.ChunkConfig(chunks=2), progress=False)
    lo, hi = street.bounds
    diag = float(np.linalg.norm(hi - lo))
    tau = TAU_FRACTION * diag
    f_single = metrics.roi_f_score(single.mesh, street.gt_mesh, lo, hi, tau, n_samples=20000).f_score
    f_chunks = metrics.roi_f_score(res.mesh, street.gt_mesh, lo, hi, tau, n_samples=20000).f_score
    cd = metrics.chamfer(res.mesh, single.mesh, n_samples=20000).chamfer / diag
    print(f"2-chunk vs single fit: F1 {f_chunks:.3f} vs {f_single:.3f}, Chamfer {100 * cd:.2f} % of the ROI diagonal")
    assert f_chunks >= f_single - F1_TOLERANCE, (f_chunks, f_single)
    assert cd < CHAMFER_TOLERANCE, cd
    for name in ("mesh.ply", "surfels.ply", "report.json", "chunk_plan.json", "chunks/0/chunk.json",
                 "chunks/1/mesh.ply"):
        assert (tmp_path / name).exists(), name
    rep = json.loads((tmp_path / "report.json").read_text())
    assert [c["index"] for c in rep["per_chunk"]] == [0, 1] and rep["per_rank"][0]["peak_rss_bytes"] > 0
    again = wc.fit_chunked(street, tmp_path, cfg, chunk_config=wc.ChunkConfig(chunks=2), progress=False)
    assert all(c.get("resumed") for c in again.report["per_chunk"])  # finished chunks are not fitted again


def _sphere_surfels(center, radius: float, n: int):
    """``n`` opaque surfels tiling a sphere (Fibonacci lattice, radial normals): world-frame arrays as
    :func:`wtopo.chunks.merge_surfels` gives them."""
    from wtopo.fitting.surfels import normals_to_quats

    nrm, p, sigma = sphere_lattice(n, radius)
    quats = normals_to_quats(torch.as_tensor(nrm, dtype=torch.float32)).numpy()
    return (np.asarray(center) + p).astype(np.float32), quats, np.full((n, 2), sigma, np.float32), \
        np.full(n, 0.95, np.float32), np.zeros((n, 1, 3), np.float32)


def test_refused_merge_is_closed_across_the_cut_and_in_the_world_frame():
    """Re-fuse a sphere's surfels over a 2-chunk plan cut through it: no open edge at the cut, world frame."""
    from wtopo.camera import Camera
    from wtopo.chunks.merge import boundary_edges_near

    center, radius = np.array([40.0, -25.0, 3.0]), 2.0  # far from the origin, not unit sized
    rig = [(a, h) for h in (-5.0, 0.0, 5.0) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    cams = [Camera.look_at(center + [7 * np.cos(a), 7 * np.sin(a), h], center, [0, 0, 1], fov_x=0.9, width=48,
                           height=36, name=f"v{i}") for i, (a, h) in enumerate(rig)]
    scene = Scene(cams, np.full((len(cams), 36, 48, 3), 0.5, np.float32), bounds=(center - 2.6, center + 2.6))
    cfg = _tiny_config()
    plan = wc.plan_chunks(scene, wc.ChunkConfig(chunks=2, min_views=1), fit_config=cfg)
    # each chunk keeps the cameras on its side (every camera sees both halves here): each view fuses only
    # its chunk's core, so the surface at the cut is fused from the two sides' views
    x = np.array([c.center[0] for c in cams])
    plan.chunks[0].cameras = np.nonzero(x <= center[0] + 0.1)[0].tolist()
    plan.chunks[1].cameras = np.nonzero(x >= center[0] - 0.1)[0].tolist()
    mesh, info = wc.refuse_mesh(scene, _sphere_surfels(center, radius, 3000), cfg, resolution=48, device="cpu",
                                plan=plan)
    (axis, cut), = plan.cuts()
    assert axis == 0 and abs(cut - center[0]) < 1e-9  # the cut goes through the sphere
    assert boundary_edges_near(mesh, plan.cuts(), radius) == 0
    assert mesh.is_watertight
    # on the sphere within a voxel (5.72 * 1.1 / 48 = 0.13 world units; silhouette pixels render a few
    # vertices up to 2.5 voxels off): the world frame, not the internal one (unit cube)
    r = np.linalg.norm(mesh.vertices - center, axis=1)
    np.testing.assert_allclose(np.median(r), radius, atol=info["voxel"])
    np.testing.assert_allclose(mesh.vertices.mean(axis=0), center, atol=info["voxel"])


def test_refuse_resolution_keeps_the_finest_chunk_voxel():
    """Scale the chunks' final resolution by the region over the box side, capped, never below the chunks'."""
    plan = _plan([0, 0, 0], [10, 2, 2], (2, 1, 1), overlap=0.25)  # boxes 6.25 wide
    assert wc.refuse_resolution(plan, {0: 100, 1: 80}) == 160
    assert wc.refuse_resolution(plan, {0: 4000}) == wc.merge.MAX_REFUSE_RESOLUTION


@pytest.mark.slow
def test_refused_merge_has_no_seam_and_chunks_skip_their_mesh(street, tmp_path, monkeypatch):
    """Leave no more open edges at the cut than one fit at the same voxel; chunks build no mesh unless welding.

    The per-face view-support rule is off here: it drops regions of these 20-iteration fits' meshes wherever their
    surface disagrees with the views, which changes the open edges of each mesh by where it cuts, not by the seam.
    """
    import wtopo.fitting._final_mesh as final
    from wtopo.chunks.merge import boundary_edges_near

    monkeypatch.setattr(final, "supported_faces", lambda mesh, *args, **kwargs: (mesh, {}))

    cfg = _tiny_config()
    refused = wc.fit_chunked(street, tmp_path / "refuse", cfg, chunk_config=wc.ChunkConfig(chunks=2), progress=False)
    welded = wc.fit_chunked(street, tmp_path / "weld", cfg, chunk_config=wc.ChunkConfig(chunks=2, merge="weld"),
                            progress=False)
    m = refused.report["merge"]
    assert m["method"] == "refuse" and welded.report["merge"]["method"] == "weld"
    assert m["near"] == pytest.approx(wc.merge.chunk_near(street, refused.plan), rel=1e-6)
    for c in refused.report["per_chunk"]:  # the merge re-fuses: no chunk paid for a mesh
        assert c["faces"] == 0 and c["final_s"] == 0.0, c
        assert "final" not in json.loads((tmp_path / "refuse" / "chunks" / str(c["index"]) / "report.json")
                                         .read_text())["stage_times_s"]
    assert all(c["faces"] > 0 for c in welded.report["per_chunk"])
    one = small_fit_config(20, 0, points=300, grids=(32, m["resolution"], 32), max_faces=800, density_every=10,
                           eval_every=0)
    single = fit(street, one, progress=False)  # one fit whose final voxel is the merge's
    seam = {k: boundary_edges_near(r.mesh, refused.plan.cuts(), m["band"][0])
            for k, r in (("refuse", refused), ("weld", welded), ("single", single))}
    print(f"open edges within {m['band'][0]:.2f} of the cut: {seam}")
    assert seam["refuse"] == m["open_edges_near_cuts"]
    assert seam["refuse"] <= seam["single"] and seam["refuse"] < seam["weld"], seam
    lo, hi = street.bounds
    assert np.all(refused.mesh.bounds[0] >= lo - 1e-6) and np.all(refused.mesh.bounds[1] <= hi + 1e-6)  # world frame


def _worker(rank: int, world: int, port: int, out: str) -> None:
    import faulthandler

    import torch.distributed as dist

    # a native abort writes every thread's Python stack to this file (kept open to the process's end),
    # which the test reports
    faulthandler.enable(file=open(os.path.join(out, f"rank{rank}.faults"), "w"))  # noqa: SIM115
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), LOCAL_RANK=str(rank))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        scene = wc.street_scene(2, orbit_views=4, forward_views=4, resolution=(24, 18), points=500)
        cfg = small_fit_config(4, 0, points=100, grids=(16, 16, 16), max_faces=200, density_every=10, eval_every=0)
        wc.fit_chunked(scene, out, cfg, chunk_config=wc.ChunkConfig(chunks=2), progress=False)
        dist.barrier()  # no rank tears its gloo pairs down while the other still uses them
        with open(os.path.join(out, f"rank{rank}.past_barrier"), "w") as f:
            f.write("both ranks finished the fit and the merge\n")
    finally:
        dist.destroy_process_group()


@pytest.mark.slow
def test_two_processes_share_the_chunks_through_gloo(tmp_path):
    """Run world size 2 on gloo (torch.multiprocessing): each rank fits one chunk, rank 0 merges.

    A rank that aborts once both ranks are past the closing barrier (the gloo teardown, torch's own
    code) is reported as a warning, an abort before it fails the test. CI saw rank 1 end with
    ``terminate called without an active exception`` (SIGABRT) twice, with no stack to say where; the
    workers now write one (faulthandler) and the test reports it.
    """
    import socket
    import warnings

    from torch.multiprocessing import ProcessExitedException

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    try:
        torch.multiprocessing.spawn(_worker, args=(2, port, str(tmp_path)), nprocs=2, join=True)
    except ProcessExitedException as e:
        stacks = "".join(f"\n{p.name}:\n{p.read_text()}" for p in sorted(tmp_path.glob("rank*.faults"))
                         if p.read_text().strip())
        if e.signal_name != "SIGABRT" or not list(tmp_path.glob("rank*.past_barrier")):
            raise AssertionError(f"{e} (before the closing barrier or not SIGABRT); its stacks:{stacks}") from e
        warnings.warn(f"rank {e.error_index} aborted in the gloo teardown after the closing barrier: {e}; "
                      f"its stacks:{stacks}", stacklevel=1)
    else:
        assert sorted(p.name for p in tmp_path.glob("rank*.past_barrier")) == ["rank0.past_barrier",
                                                                                 "rank1.past_barrier"]
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["world_size"] == 2
    assert {c["index"]: c["rank"] for c in rep["per_chunk"]} == {0: 0, 1: 1}
    assert (tmp_path / "mesh.ply").exists()


def test_chunk_runs_its_share_of_the_iteration_budget():
    """Scale iterations by the chunk's view share and point budgets by its space share (configured or planned)."""
    from wtopo.chunks.engine import chunk_fit_config
    from wtopo.fitting import FitConfig, Preset

    c = chunk_fit_config(_tiny_config(warmup=20), "cpu", 0.5)
    assert (c.warmup.iterations, c.coevolution.iterations, c.runtime.device) == (10, 0, "cpu")
    d = chunk_fit_config(FitConfig(), "cpu", 0.25, 0.5)
    assert (d.warmup.iterations, d.coevolution.iterations) == (100, 100)  # the CPU balanced budget 400 + 400
    cfg = FitConfig()
    cfg.preset = Preset.BEST  # the preset's budget is what the share divides
    b = chunk_fit_config(cfg, "cpu", 0.25)
    assert (b.warmup.iterations, b.coevolution.iterations) == (200, 200)  # best: 800 + 800
    # half the space: half the CPU surfel cap (40k) and re-initialisation faces (8k), half the points
    assert (d.runtime.max_surfels, d.tsdf.max_faces, d.init.num_points) == (20000, 4000, 2500)
    assert d.init.background_points is None  # left to the plan (as many as num_points for a scene)
    # the whole scene's planned budget (a CPU plan scales it with the pixels to fit) is what the share divides
    e = chunk_fit_config(FitConfig(), "cpu", 0.5, budget=(1250, 625))
    assert (e.warmup.iterations, e.coevolution.iterations) == (625, 312)


def test_cli_rejects_a_bad_chunk_count(tmp_path, capsys):
    """Report ``--chunks 0`` as a one-line user error before any scene is loaded."""
    from wtopo.cli import main

    assert main(["fit", "sphere", "--out", str(tmp_path), "--chunks", "0"]) == 2
    assert "--chunks takes a number of chunks >= 1 or 'auto', got '0'" in capsys.readouterr().err


def test_cli_passes_the_merge_choice(tmp_path, monkeypatch, capsys):
    """``--chunk-merge weld`` reaches the chunk configuration (default ``refuse``); a bad choice is a user error."""
    from wtopo.cli import main

    seen = []
    monkeypatch.setattr(wc, "fit_chunked", lambda scene, out, cfg, chunk_config, progress: seen.append(chunk_config))
    assert main(["fit", "sphere", "--out", str(tmp_path / "a"), "--chunks", "2", "--chunk-merge", "weld"]) == 0
    assert main(["fit", "sphere", "--out", str(tmp_path / "b"), "--chunks", "2"]) == 0
    assert [c.merge for c in seen] == ["weld", "refuse"] and seen[0].chunks == 2
    with pytest.raises(SystemExit) as e:
        main(["fit", "sphere", "--out", str(tmp_path / "c"), "--chunks", "2", "--chunk-merge", "glue"])
    assert e.value.code == 2 and "glue" in capsys.readouterr().err


def test_a_failing_chunk_is_reported_by_name(tmp_path, monkeypatch):
    """Raise one error naming the chunk when its fit fails, and leave no result directory for it."""
    import wtopo.fitting

    def boom(*a, **k):
        raise ValueError("no surfels left")

    monkeypatch.setattr(wtopo.fitting, "fit", boom)
    monkeypatch.setattr(wtopo.fitting, "fit_surfels", boom)  # the default merge re-fuses: chunks skip their mesh
    with pytest.raises(RuntimeError, match=r"chunk 0 \(rank 0\): ValueError: no surfels left"):
        wc.fit_chunked(_camera_scene(), tmp_path, _tiny_config(), chunk_config=wc.ChunkConfig(chunks=3),
                       progress=False)
    assert not (tmp_path / "chunks" / "0").exists() and (tmp_path / "chunk_plan.json").exists()


def test_an_interrupted_chunk_is_not_taken_as_done(tmp_path, monkeypatch):
    """Keep an interrupted chunk's partial directory (to resume) and publish no result for it."""
    import types

    import wtopo.fitting

    def interrupted(scene, cfg, out_dir=None, progress=True):
        os.makedirs(out_dir, exist_ok=True)
        return types.SimpleNamespace(mesh=trimesh.creation.box(), report={"status": "interrupted"})

    monkeypatch.setattr(wtopo.fitting, "fit", interrupted)
    monkeypatch.setattr(wtopo.fitting, "fit_surfels", interrupted)
    with pytest.raises(RuntimeError, match="status 'interrupted'; a rerun resumes it"):
        wc.fit_chunked(_camera_scene(), tmp_path, _tiny_config(), chunk_config=wc.ChunkConfig(chunks=3),
                       progress=False)
    assert (tmp_path / "chunks" / "0.partial").is_dir() and not (tmp_path / "chunks" / "0").exists()


def test_refused_merge_meshes_with_the_chunks_near_distance(street):
    """The re-fused merge keeps faces as near the cameras as each chunk's fit would (the whole scene's
    near distance, 5 % of its larger extent, would drop the ground under the cameras)."""
    from wtopo.chunks.merge import chunk_near
    from wtopo.fitting.scene_kind import analyse_layout

    plan = wc.plan_chunks(street, wc.ChunkConfig(chunks=2))
    near = chunk_near(street, plan)
    whole = analyse_layout(street.normalized()).near / street.normalization().scale
    per_chunk = []
    for ch in plan.chunks:
        sub = wc.chunk_scene(street, ch)
        per_chunk.append(analyse_layout(sub.normalized()).near / sub.normalization().scale)
    assert near == pytest.approx(min(per_chunk)) and near < whole, (near, per_chunk, whole)
