# SPDX-License-Identifier: Apache-2.0
"""Real-capture behaviour of the fit: scene kinds, background without masks, PSNR without ground truth."""

import numpy as np
import pytest
import torch
import trimesh
from fit_configs import small_fit_config

import wtopo
from wtopo import scenes
from wtopo.fitting import FitConfig
from wtopo.fitting.plan import make_plan, resolve_config
from wtopo.fitting.presets import budget
from wtopo.fitting.scene_kind import NEAR_FRACTION
from wtopo.metrics import camera_clearance


def _small(warmup=40, coevolution=12):
    return small_fit_config(warmup, coevolution, points=600, grids=(48, 64, 32), max_faces=1500, density_every=10,
                            eval_every=20)


@pytest.fixture(scope="module")
def room():
    """A sphere in a textured room, 12 orbit views of 32 px plus 2 held out, no masks."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    return scenes.from_mesh(mesh, n_views=12, resolution=32, rig="orbit", background="room", n_test=2,
                            texture="coffee", name="room")


def test_plan_tells_objects_from_scenes(room):
    """Decide 'scene' without masks and 'object' with masks; honour an explicit kind."""
    dev = torch.device("cpu")
    p = make_plan(room.normalized(), FitConfig(), dev)
    assert p.scene_kind == "scene" and p.mesh_policy == "open_roi" and p.background_points > 0
    assert "360" in p.reasons["scene_kind"]
    assert p.densify and "gradient" in p.reasons["densify"]  # no coverage gap to wait for
    masked = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24)
    q = make_plan(masked.normalized(), FitConfig(), dev)
    assert q.scene_kind == "object" and q.mesh_policy == "watertight" and q.background_points == 0
    cfg = FitConfig()
    cfg.kind = "object"
    assert make_plan(room.normalized(), cfg, dev).scene_kind == "object"


def test_plan_runs_the_mesh_loop_and_the_reinit_for_objects_only(room):
    """Leave the proxy-mesh loop out for a scene and with it the TSDF re-initialisation (its reason printed; the
    background rule needs no TSDF mesh); run both for an object and for a scene with the loop; honour explicit
    settings."""
    dev = torch.device("cpu")
    p = make_plan(room.normalized(), FitConfig(), dev)
    assert p.mesh_loop is False and "scene" in p.reasons["mesh_loop"]
    assert p.tsdf_reinit is False and "proxy-mesh loop" in p.reasons["tsdf_reinit"] and "skipped" in str(p)
    assert p.background_rule is True
    resolved = resolve_config(FitConfig(), p)
    assert resolved.coevolution.enabled is False and resolved.tsdf.enabled is False
    masked = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24)
    q = make_plan(masked.normalized(), FitConfig(), dev)
    assert q.mesh_loop is True and q.tsdf_reinit is True
    cfg = FitConfig()
    cfg.coevolution.enabled = True
    p = make_plan(room.normalized(), cfg, dev)
    assert p.mesh_loop is True and "mesh_loop" in p.overrides and p.tsdf_reinit is True
    cfg = FitConfig()
    cfg.tsdf.enabled = True
    p = make_plan(room.normalized(), cfg, dev)
    assert p.mesh_loop is False and p.tsdf_reinit is True and "tsdf_reinit" in p.overrides


def test_scene_fit_without_reinit_keeps_its_warm_up_surfels(room):
    """The co-evolution of a scene goes on from the warm-up's own surfels: no re-initialisation event, no TSDF
    record, and the warm-up's surfel count carries over (nothing was replaced by one surfel per face)."""
    res = wtopo.fit(room, _small(warmup=20, coevolution=4), progress=False)
    assert "tsdf_reinit" not in {e["event"] for e in res.report["events"]}
    stages = [h["stage"] for h in res.history]
    assert "tsdf" not in stages and stages[0] == "warmup" and res.history[0]["iteration"] == 20
    assert res.history[-1]["surfels"] == res.history[0]["surfels"] and len(res.mesh.faces) > 0


def test_plan_gives_a_scene_an_open_proxy(room):
    """A scene's proxy takes a local zero level and is clipped to the region of interest; an object's keeps
    one level and its whole proxy; explicit settings win and reach the resolved configuration."""
    dev = torch.device("cpu")
    p = make_plan(room.normalized(), FitConfig(), dev)
    assert p.proxy_level_sigma > 0 and p.proxy_clip is True
    masked = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24)
    q = make_plan(masked.normalized(), FitConfig(), dev)
    assert q.proxy_level_sigma == 0 and q.proxy_clip is False
    cfg = FitConfig()
    cfg.mesh.level_sigma, cfg.mesh.clip_to_region = 0.0, False
    p = make_plan(room.normalized(), cfg, dev)
    assert p.proxy_level_sigma == 0 and "proxy_level_sigma" in p.overrides
    r = resolve_config(cfg, p)
    assert r.mesh.level_sigma == 0 and r.mesh.clip_to_region is False
    r = resolve_config(FitConfig(), make_plan(room.normalized(), FitConfig(), dev))
    assert r.mesh.level_sigma > 0
    assert r.mesh.clip_to_region is True


def test_plan_budget_follows_the_device(room):
    """Give CUDA a larger budget than the CPU; honour an explicit image scale."""
    cpu = make_plan(room.normalized(), FitConfig(), torch.device("cpu"))
    gpu = make_plan(room.normalized(), FitConfig(), torch.device("cuda"))
    for k in ("warmup_iterations", "coevolution_iterations", "max_surfels", "proxy_resolution"):
        assert getattr(gpu, k) > getattr(cpu, k), k
    assert gpu.reinit_faces >= cpu.reinit_faces  # the same footprint rule, a larger cap
    assert gpu.reinit_faces < gpu.max_surfels  # room to densify after the re-initialisation
    cfg = FitConfig()
    cfg.runtime.image_scale = 0.5
    p = make_plan(room.normalized(), cfg, torch.device("cpu"))
    assert p.image_scale == 0.5 and "image_scale" in p.overrides


def test_cuda_plan_holds_the_means_rate_at_its_floor_for_the_co_evolutions_second_half(room):
    """CUDA: the means' decay ends halfway through the co-evolution (3,000 + 2,000: at 4,000, the horizon of the
    former 3,000 + 1,000, whose warm-ups it shares); the CPU decays over the whole fit; a user's horizon wins,
    and a user's co-evolution length moves the plan's horizon with it."""
    from wtopo.fitting import plan as P
    from wtopo.fitting.checkpointing import warmup_differences

    scene = room.normalized()
    gpu = make_plan(scene, FitConfig(), torch.device("cuda"))
    warm, coevo = budget("balanced", "cuda").iterations
    assert gpu.means_decay_iterations == warm + round(P._MEANS_DECAY_COEVO["cuda"] * coevo) < warm + coevo
    assert resolve_config(FitConfig(), gpu).optim.means_decay_iterations == gpu.means_decay_iterations
    cpu = make_plan(scene, FitConfig(), torch.device("cpu"))
    assert cpu.means_decay_iterations is None
    assert resolve_config(FitConfig(), cpu).optim.means_decay_iterations is None
    cfg = FitConfig()
    cfg.optim.means_decay_iterations = 1234
    p = make_plan(scene, cfg, torch.device("cuda"))
    assert p.means_decay_iterations == 1234 and "means_decay_iterations" in p.overrides
    cfg = FitConfig()
    cfg.coevolution.iterations = 600
    assert make_plan(scene, cfg, torch.device("cuda")).means_decay_iterations == warm + 300
    # the former CUDA default (3,000 + 1,000, decayed over all of it) fitted the same warm-up
    new = resolve_config(FitConfig(), gpu)
    old = resolve_config(FitConfig(), gpu)
    old.coevolution.iterations, old.optim.means_decay_iterations = 1000, None
    assert (warm, coevo) == (3000, 2000) and warmup_differences(old.to_dict(), new.to_dict()) == []
    old.coevolution.iterations = 1500  # another horizon: another warm-up
    assert warmup_differences(old.to_dict(), new.to_dict()) == ["coevolution.iterations",
                                                               "optim.means_decay_iterations"]


def test_cuda_plan_restarts_the_co_evolutions_means_and_the_cpu_does_not(room):
    """CUDA: the co-evolution's means restart at 1e-4 (0.0625 of ``optim.means``) and decay to their floor at the
    fit's end; the CPU keeps the single decay; a user's value wins; the restart acts after the warm-up, so a fit
    without it branches from the default's warm-up."""
    from wtopo.fitting import plan as P
    from wtopo.fitting.checkpointing import warmup_differences
    from wtopo.fitting.schedule import means_rate

    scene = room.normalized()
    gpu = make_plan(scene, FitConfig(), torch.device("cuda"))
    assert gpu.means_restart == P._MEANS_RESTART["cuda"] == 0.0625
    o = resolve_config(FitConfig(), gpu).optim
    assert o.means_restart == 0.0625
    warm, coevo = budget("balanced", "cuda").iterations
    assert means_rate(o, warm, warm, warm + coevo) == pytest.approx(1e-4)
    assert means_rate(o, warm - 1, warm, warm + coevo) < 6e-5  # the warm-up keeps its decay
    cpu = make_plan(scene, FitConfig(), torch.device("cpu"))
    assert cpu.means_restart == 0.0 and resolve_config(FitConfig(), cpu).optim.means_restart == 0.0
    cfg = FitConfig()
    cfg.optim.means_restart = 0.0
    p = make_plan(scene, cfg, torch.device("cuda"))
    assert p.means_restart == 0.0 and "means_restart" in p.overrides
    assert warmup_differences(resolve_config(cfg, p).to_dict(), resolve_config(FitConfig(), gpu).to_dict()) == []


def test_plan_picks_the_render_filter_per_device_and_a_users_wins(room):
    """The renderer's low-pass is the plan's: 0.25 px on CUDA, 0.35 on the CPU (design/decisions.md); the resolved
    configuration, which the fit renders with, carries it; a user's value wins on either device."""
    scene = room.normalized()
    for dev, want in (("cuda", 0.25), ("cpu", 0.35)):
        p = make_plan(scene, FitConfig(), torch.device(dev))
        assert p.filter_sigma == want and "filter_sigma" not in p.overrides
        assert resolve_config(FitConfig(), p).filter_sigma == want
        assert p.to_dict()["filter_sigma"]["value"] == want
    cfg = FitConfig(filter_sigma=0.5)
    for dev in ("cuda", "cpu"):
        p = make_plan(scene, cfg, torch.device(dev))
        assert p.filter_sigma == 0.5 and "filter_sigma" in p.overrides
        assert resolve_config(cfg, p).filter_sigma == 0.5


def test_reinit_faces_follow_the_pixel_footprint():
    """Put about one re-initialisation face per 4 squared pixel footprints of the region's box surface on
    CUDA (a 32-view rig sees the surface from enough views for the full density): 2x the image side gives
    about 4x the faces between the CPU default's count and the cap; the CPU keeps its count; a user's count
    wins."""
    import re

    from wtopo.fitting.plan import _REINIT_DENSITY, _REINIT_FACES, _REINIT_MIN

    mesh = trimesh.creation.icosphere(subdivisions=2)

    def plan(res, device="cuda", cfg=None):  # the plan only reads the device's kind
        return make_plan(scenes.from_mesh(mesh, n_views=32, resolution=res).normalized(), cfg or FitConfig(),
                         torch.device(device))

    faces, box = {}, {}
    for res in (128, 256):
        p = plan(res)
        faces[res] = p.reinit_faces
        box[res] = float(re.search(r"\((\d+) footprint", p.reasons["reinit_faces"]).group(1))
            # a 32-view sphere rig sees each point of the region from 12 views: the full density
        assert "times 1.00" in p.reasons["reinit_faces"]
        # (the reason prints the box rounded to a footprint^2)
        assert faces[res] == pytest.approx(np.clip(_REINIT_DENSITY * box[res], _REINIT_MIN, _REINIT_FACES["cuda"]),
                                           abs=1)
    assert _REINIT_MIN < faces[128] < faces[256] < _REINIT_FACES["cuda"]  # the rule, not a bound, decided both
    # a footprint 2x smaller; the region of interest is found from the images, a little looser at 128 px
    assert box[256] / box[128] == pytest.approx(4.0, rel=0.1)
    assert faces[256] / faces[128] == pytest.approx(box[256] / box[128], rel=0.01)
    assert plan(24).reinit_faces == _REINIT_MIN  # a small image: the floor
    assert plan(512).reinit_faces == _REINIT_FACES["cuda"]  # capped
    assert plan(24, "cpu").reinit_faces == plan(512, "cpu").reinit_faces == _REINIT_FACES["cpu"]
    cfg = FitConfig()
    cfg.tsdf.max_faces = 1234
    p = plan(64, cfg=cfg)
    assert p.reinit_faces == 1234 and "reinit_faces" in p.overrides


def _cameras_around(directions, distance=4.0, resolution=32, fov=0.9):
    return [wtopo.Camera.look_at(distance * np.asarray(d, np.float64) / np.linalg.norm(d), np.zeros(3),
                                 (0, 0, 1) if abs(d[2]) < 0.9 * np.linalg.norm(d) else (0, 1, 0), fov_x=fov,
                                 width=resolution, height=resolution) for d in directions]


def _cube_layout():
    from types import SimpleNamespace  # views_per_point reads only the region's box and centre

    return SimpleNamespace(roi_lower=-np.ones(3), roi_upper=np.ones(3), roi_center=np.zeros(3))


def test_views_per_point_counts_the_views_facing_each_direction():
    """Closed forms: one view sees the directions within ~75.5 degrees of it once (mean 1); two views at the
    same place, twice; a view looking away or held out counts nothing; six axis views see a direction with
    |n_i| > 0.25 from each of those axes (counted exactly here)."""
    from wtopo.fitting.plan import _VIEW_FACING, views_per_point

    lay = _cube_layout()
    imgs = torch.zeros(2, 32, 32, 3)
    one = wtopo.Scene(_cameras_around([(1, 0.2, 0.1)]), imgs[:1])
    assert views_per_point(one, lay) == pytest.approx(1.0)
    two = wtopo.Scene(_cameras_around([(1, 0.2, 0.1)] * 2), imgs)
    assert views_per_point(two, lay) == pytest.approx(2.0)
    split = wtopo.Scene(_cameras_around([(1, 0.2, 0.1)] * 2), imgs, train_indices=[0], test_indices=[1])
    assert views_per_point(split, lay) == pytest.approx(1.0)
    away = _cameras_around([(1, 0, 0)])[0]
    turned = wtopo.Camera.look_at(away.center, 2 * away.center, (0, 0, 1), fov_x=0.9, width=32, height=32)
    assert views_per_point(wtopo.Scene([turned], imgs[:1]), lay) == 0.0
    axes = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    six = wtopo.Scene(_cameras_around(axes), torch.zeros(6, 32, 32, 3))
    n = 512
    k = np.arange(n) + 0.5
    polar, azim = np.arccos(1 - 2 * k / n), np.pi * (1 + 5 ** 0.5) * k
    u = np.stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar), np.cos(polar)], axis=1)
    count = (u > _VIEW_FACING).sum(axis=1) + (-u > _VIEW_FACING).sum(axis=1)
    assert views_per_point(six, lay, samples=n) == pytest.approx(count[count > 0].mean())
    assert 1.5 < views_per_point(six, lay) < 2.5  # a direction meets one to three axes


def test_reinit_faces_fall_with_the_views_that_see_the_surface():
    """Ten views of a sphere rig see each point from ~3.8 views against the 32-view rig's 12: the same
    footprint rule gets views / 11.5 of its faces; 32 and 64 views keep the full density."""
    import re

    from wtopo.fitting.plan import _REINIT_DENSITY, _REINIT_VIEWS, views_per_point
    from wtopo.fitting.scene_kind import analyse_layout

    mesh = trimesh.creation.icosphere(subdivisions=2)
    dev = torch.device("cuda")  # the plan only reads the device's kind
    out = {}
    for n in (10, 32, 64):
        sc = scenes.from_mesh(mesh, n_views=n, resolution=256).normalized()
        p = make_plan(sc, FitConfig(), dev)
        box = float(re.search(r"\((\d+) footprint", p.reasons["reinit_faces"]).group(1))
        v = views_per_point(sc, analyse_layout(sc))
        out[n] = (p.reinit_faces, box, v)
    f10, box10, v10 = out[10]
    assert 3.0 < v10 < 4.5 and out[32][2] >= _REINIT_VIEWS and out[64][2] > 20
    # between the floor and the cap (the reason prints the box rounded)
    assert f10 == pytest.approx(_REINIT_DENSITY * box10 * v10 / _REINIT_VIEWS, abs=1)
    assert f10 < _REINIT_DENSITY * box10 / 2  # the view count, not a bound, cut it
    for n in (32, 64):
        assert out[n][0] == pytest.approx(_REINIT_DENSITY * out[n][1], abs=1)  # full density


def test_plan_counts_only_the_training_views():
    """Held-out photographs do not count as training views: 18 training views plus 6 held out get
    no view-dependent colour (fewer than 20), and so do 22 views of which the fit holds 4 out (the
    split the fit trains on has those sizes)."""
    from wtopo.fitting.loop import _split_views
    from wtopo.fitting.plan import _MIN_SH_VIEWS, split_views

    mesh = trimesh.creation.icosphere(subdivisions=2)
    dev = torch.device("cpu")
    split = scenes.from_mesh(mesh, n_views=18, resolution=24, n_test=6)
    held = scenes.from_mesh(mesh, n_views=22, resolution=24)
    for sc, n_train in ((split, 18), (held, 18)):
        assert len(sc.cameras) >= _MIN_SH_VIEWS  # all the photographs would pass the rule
        p = make_plan(sc.normalized(), FitConfig(), dev)
        assert p.sh_degree == 0 and f"{n_train} training views" in p.reasons["sh_degree"]
        train, test, _ = _split_views(sc, p.eval_views)
        sizes = (len(train.cameras), len(test.cameras))
        assert sizes == (n_train, len(sc.cameras) - n_train)
    big = scenes.from_mesh(mesh, n_views=26, resolution=24)  # 22 training views: enough
    assert "training views" not in make_plan(big.normalized(), FitConfig(), dev).reasons["sh_degree"]
    few = scenes.from_mesh(mesh, n_views=8, resolution=24)  # under 12 views nothing is held out
    p = make_plan(few.normalized(), FitConfig(), dev)
    assert p.eval_views == 0 and split_views(few, p.eval_views) == (list(range(8)), [])


def test_plan_gives_textured_photographs_without_depth_sh_degree_3():
    """Enough textured training views and no depth to test view dependence: degree 3 (3DGS, 2DGS); the same
    capture with depth maps is decided by how its colours reproject instead."""
    import dataclasses

    mesh = trimesh.creation.icosphere(subdivisions=2)
    dev = torch.device("cpu")
    sc = scenes.from_mesh(mesh, n_views=26, resolution=24, texture="coffee")
    assert "reprojected colours" in make_plan(sc.normalized(), FitConfig(), dev).reasons["sh_degree"]
    photos = dataclasses.replace(sc, depths=None)
    p = make_plan(photos.normalized(), FitConfig(), dev)
    assert p.sh_degree == 3 and "no depth" in p.reasons["sh_degree"]


def test_window_texture_leaves_clipped_windows_out():
    """Saturated white and black windows carry no texture to match: with 80 % of the picture clipped the
    median window std is the textured part's (the multi-view gate opens), not 0; a flat grey picture stays 0."""
    from wtopo.fitting._image_stats import window_std as _window_std
    from wtopo.fitting.plan import _MULTIVIEW_TEXTURE

    g = torch.Generator().manual_seed(0)
    img = 0.5 + 0.1 * torch.randn(4, 40, 100, 3, generator=g)  # textured: window std ~0.07
    img[:, :, :40] = 1.0  # saturated highlight
    img[:, :, 40:80] = 0.0  # black
    textured = _window_std(img.numpy(), None)
    assert textured > 2 * _MULTIVIEW_TEXTURE, textured
    assert _window_std(np.full((4, 40, 100, 3), 0.5, np.float32), None) == 0.0
    assert _window_std(np.ones((4, 40, 100, 3), np.float32), None) == 0.0  # nothing left: no texture


def test_plan_image_statistics_read_only_the_training_photographs():
    """The plan's texture statistics never read a held-out photograph: a flat grey capture whose held-out
    photographs alone carry texture is planned as untextured (no multi-view term, no view-dependent colour),
    exactly as the same capture with flat held-out photographs; with the texture in the training
    photographs instead, the plan sees it."""
    import dataclasses

    mesh = trimesh.creation.icosphere(subdivisions=2)
    dev = torch.device("cpu")
    sc = scenes.from_mesh(mesh, n_views=16, resolution=24, n_test=4)
    sc = dataclasses.replace(sc, images=torch.full_like(sc.images, 0.5))  # flat grey photographs
    test = [int(i) for i in sc.test_indices]
    g = torch.Generator().manual_seed(0)
    noise = torch.rand(sc.images.shape, generator=g, dtype=sc.images.dtype)
    held = torch.zeros(len(sc.cameras), dtype=torch.bool)
    held[test] = True
    keep = sc.masks[..., None] if sc.masks is not None else torch.ones_like(noise[..., :1], dtype=torch.bool)

    def textured(where):
        img = torch.where(where[:, None, None, None] & keep, noise, sc.images)
        return dataclasses.replace(sc, images=img)

    flat = make_plan(sc.normalized(), FitConfig(), dev)
    held_tex = make_plan(textured(held).normalized(), FitConfig(), dev)
    train_tex = make_plan(textured(~held).normalized(), FitConfig(), dev)
    assert flat.multiview == 0.0 and "shading only" in flat.reasons["multiview"]
    assert flat.sh_degree == 0 and "untextured" in flat.reasons["sh_degree"]
    for name in ("multiview", "sh_degree"):
        assert getattr(held_tex, name) == getattr(flat, name) and held_tex.reasons[name] == flat.reasons[name]
    assert train_tex.multiview > 0 and "untextured" not in train_tex.reasons["sh_degree"]


@pytest.mark.slow
def test_unbounded_scene_has_no_face_near_a_camera_and_reports_psnr(room):
    """Fit a room without masks: an open mesh away from every camera, held-out PSNR/SSIM without a gt mesh."""
    sc = wtopo.Scene(room.cameras, room.images, train_indices=room.train_indices, test_indices=room.test_indices,
                     name="room_no_gt")
    res = wtopo.fit(sc, _small(), progress=False)
    assert res.report["scene_kind"] == "scene"
    assert len(res.mesh.faces) > 50
    centers = np.stack([c.center for c in sc.cameras])
    lo, hi = sc.region_of_interest()
    extent = float(np.linalg.norm(np.ptp(np.concatenate([centers, lo[None], hi[None]]), axis=0)))
    clearance = camera_clearance(res.mesh, centers)
    assert clearance.min() >= NEAR_FRACTION * extent, (clearance.min(), extent)
    assert not res.mesh.is_watertight  # open where unobserved, never a closed hull
    last = res.history[-1]
    assert np.isfinite(last["psnr"]) and last["psnr"] > 10 and 0 < last["ssim"] <= 1
    assert last["image_metrics_on"] == "held_out" and "chamfer" not in last
    assert res.report["psnr"] == last["psnr"]
    events = {e["event"] for e in res.report["events"]}
    assert "mesh_policy" in events


def test_cpu_budget_grows_with_the_pixels_to_fit():
    """Keep 800 + 800 CPU iterations for a masked object; give an unmasked capture of the same views
    more (every pixel is to be fitted), proportionally, but never past the CPU's rendered-pixel cap."""
    from wtopo.fitting import plan as P

    dev = torch.device("cpu")
    obj = scenes.load("bunny")
    base = make_plan(obj.normalized(), FitConfig(), dev)
    assert (base.warmup_iterations, base.coevolution_iterations) == budget("balanced", "cpu").iterations
    bare = wtopo.Scene(obj.cameras, obj.images, train_indices=obj.train_indices, test_indices=obj.test_indices)
    p = make_plan(bare.normalized(), FitConfig(), dev)
    n_train = len(obj.train_indices) if obj.train_indices is not None else len(obj)
    warm, coevo = budget("balanced", "cpu").iterations
    k = min(n_train * 128 * 128 / P._CPU_FIT_PIXELS, P._CPU_RENDER_PIXELS / (warm * 128 * 128))
    assert k > 1.5 and p.warmup_iterations == round(warm * k) and p.coevolution_iterations == round(coevo * k)
    assert "training pixels" in p.reasons["warmup_iterations"]
    # the same rule outside the plan (chunked fits divide the whole scene's budget), any frame
    assert P.iteration_budget(bare, dev)[:2] == (p.warmup_iterations, p.coevolution_iterations)
    cfg = FitConfig()
    cfg.warmup.iterations = 123  # an explicit budget is honoured
    assert make_plan(bare.normalized(), cfg, dev).warmup_iterations == 123
    # 512 px (trained at 256 on a CPU): the base warm-up's views already render past the cap
    up = torch.nn.functional.interpolate(obj.images.permute(0, 3, 1, 2), scale_factor=4).permute(0, 2, 3, 1)
    big = wtopo.Scene([c.scaled(4.0) for c in obj.cameras], up, train_indices=obj.train_indices,
                      test_indices=obj.test_indices)
    assert make_plan(big.normalized(), FitConfig(), dev).warmup_iterations == warm


def test_resumed_scene_fit_keeps_the_clipped_proxy(room, tmp_path):
    """A scene fit with the loop stopped in the co-evolution resumes with its proxy clipped to the region of
    interest and its local level (the checkpoint rebuilds the proxy from the resolved configuration)."""
    from wtopo.fitting.loop import FitRun

    cfg = _small(warmup=20, coevolution=10)
    cfg.coevolution.enabled = True
    cfg.runtime.checkpoint_every = 2
    cfg.runtime.stop_at = 24
    first = FitRun(room, cfg, tmp_path, progress=False)
    first.run()
    assert first.proxy.clip is not None and first.proxy.cfg.level_sigma > 0
    again = FitRun(room, cfg, tmp_path, progress=False)
    again._start()
    assert again.it == 24
    for a, b in zip(again.proxy.clip, (again.plan.layout.roi_lower, again.plan.layout.roi_upper)):
        np.testing.assert_array_equal(a, b)
    assert again.proxy.cfg.level_sigma == first.proxy.cfg.level_sigma
