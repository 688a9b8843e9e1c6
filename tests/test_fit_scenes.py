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
    assert p["scene_kind"] == "scene" and p["mesh_policy"] == "open_roi" and p["background_points"] > 0
    assert "360" in p.decisions["scene_kind"].reason
    assert p["densify"] and "gradient" in p.decisions["densify"].reason  # no coverage gap to wait for
    masked = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24)
    q = make_plan(masked.normalized(), FitConfig(), dev)
    assert q["scene_kind"] == "object" and q["mesh_policy"] == "watertight" and q["background_points"] == 0
    cfg = FitConfig()
    cfg.kind = "object"
    assert make_plan(room.normalized(), cfg, dev)["scene_kind"] == "object"


def test_plan_runs_the_mesh_loop_for_objects_only(room):
    """Leave the proxy-mesh loop out for a scene, run it for an object, honour an explicit setting."""
    dev = torch.device("cpu")
    p = make_plan(room.normalized(), FitConfig(), dev)
    assert p["mesh_loop"] is False and "scene" in p.decisions["mesh_loop"].reason
    masked = scenes.from_mesh(trimesh.creation.icosphere(subdivisions=2), n_views=8, resolution=24)
    assert make_plan(masked.normalized(), FitConfig(), dev)["mesh_loop"] is True
    cfg = FitConfig()
    cfg.coevolution.enabled = True
    p = make_plan(room.normalized(), cfg, dev)
    assert p["mesh_loop"] is True and p.decisions["mesh_loop"].overridden
    assert resolve_config(FitConfig(), make_plan(room.normalized(), FitConfig(), dev)).coevolution.enabled is False


def test_plan_budget_follows_the_device(room):
    """Give CUDA a larger budget than the CPU; honour an explicit image scale."""
    cpu = make_plan(room.normalized(), FitConfig(), torch.device("cpu"))
    gpu = make_plan(room.normalized(), FitConfig(), torch.device("cuda"))
    for k in ("warmup_iterations", "coevolution_iterations", "max_surfels", "proxy_resolution", "reinit_faces"):
        assert gpu[k] > cpu[k], k
    assert gpu["reinit_faces"] < gpu["max_surfels"]  # room to densify after the re-initialisation
    cfg = FitConfig()
    cfg.runtime.image_scale = 0.5
    p = make_plan(room.normalized(), cfg, torch.device("cpu"))
    assert p["image_scale"] == 0.5 and p.decisions["image_scale"].overridden


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
