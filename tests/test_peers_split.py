# SPDX-License-Identifier: Apache-2.0
"""``benchmarks/peers/_pgsr_split.py``: the TopoSurfel authors' mesh stage stopped at a checkpoint and resumed in
another process trains as the uninterrupted run does. On the CPU, with a stand-in checkout whose ``train.py``
carries state from one iteration to the next as theirs does (``GaussianModel`` attributes outside its checkpoint,
the local mask of seen splats that selects the proxy's points, a camera stack, the appearance model's optimizer,
Python's, NumPy's and torch's random numbers, a splat count that changes until densification ends)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

torch = pytest.importorskip("torch")

PEERS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "peers")

_GAUSSIAN_MODEL = '''
import numpy as np
import torch


class GaussianModel:
    def __init__(self):
        self.view_dir_accumulation = None
        self.mesh_guidance_cached_normals = None
        self.mesh_guidance_cached_reliable = None
        self.mesh_guidance_face_centroids = None
        self.mesh_guidance_face_visible = None
        self.mesh_guidance_face_normals = None

    @property
    def get_xyz(self):
        return self._xyz

    def create(self, n):
        self._xyz = torch.nn.Parameter(torch.randn(n, 3, dtype=torch.float64))

    def training_setup(self):
        self.optimizer = torch.optim.Adam([self._xyz], lr=0.05)

    def capture(self):  # their scene scale is a NumPy scalar, as here
        return (self._xyz, self.optimizer.state_dict(), np.float64(2.5))

    def restore(self, args, training_args):
        self._xyz, opt, self.spatial_lr_scale = args
        self.training_setup()
        self.optimizer.load_state_dict(opt)

    def update_learning_rate(self, iteration):
        self.optimizer.param_groups[0]["lr"] = 0.05 / (1 + 0.01 * iteration)

    def decay_view_dir_stats(self, decay):
        if self.view_dir_accumulation is not None:
            self.view_dir_accumulation.mul_(decay)

    def add_view_dir_stat(self, cam_center, visibility_filter):
        if self.view_dir_accumulation is None or self.view_dir_accumulation.shape[0] != self._xyz.shape[0]:
            self.view_dir_accumulation = torch.zeros_like(self._xyz.detach())
        d = cam_center - self._xyz.detach()
        self.view_dir_accumulation[visibility_filter] += d[visibility_filter]

    def extract_oriented_pointcloud(self, opacity_threshold=0.0, visibility_mask=None):
        return self._xyz[visibility_mask]

    def set_mesh_guidance(self, face_centroids, face_visible=None, face_normals=None):
        self.mesh_guidance_face_centroids = face_centroids.detach()
        self.mesh_guidance_face_visible = face_visible
        self.mesh_guidance_face_normals = face_normals.detach()

    def update_mesh_normal_cache(self):
        d = self._xyz.detach()[:, None] - self.mesh_guidance_face_centroids[None]
        near = d.norm(dim=-1).argmin(1)
        self.mesh_guidance_cached_normals = self.mesh_guidance_face_normals[near]
        self.mesh_guidance_cached_reliable = self.mesh_guidance_face_visible[near]

    def normals(self):
        n = torch.nn.functional.normalize(self._xyz, dim=1)
        if self.mesh_guidance_cached_normals is not None and self.mesh_guidance_cached_normals.shape == n.shape:
            n = torch.where(self.mesh_guidance_cached_reliable[:, None], self.mesh_guidance_cached_normals, n)
        if self.view_dir_accumulation is not None:
            n = n * torch.sign((n * self.view_dir_accumulation).sum(1, keepdim=True) + 1e-12)
        return n

    def densify(self):
        pick = torch.randperm(self._xyz.shape[0])[:3]
        new = torch.cat([self._xyz.detach(), self._xyz.detach()[pick] + 0.01 * torch.randn(3, 3, dtype=torch.float64)])
        self._xyz = torch.nn.Parameter(new)
        self.training_setup()
'''

_APP_MODEL = '''
import os
import torch


class AppModel(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(3, dtype=torch.float64))
        self.optimizer = torch.optim.Adam([self.w], lr=0.01)

    def save_weights(self, model_path, iteration):
        os.makedirs(os.path.join(model_path, f"app_model/iteration_{iteration}"), exist_ok=True)
        torch.save(self.state_dict(), os.path.join(model_path, f"app_model/iteration_{iteration}/app.pth"))

    def load_weights(self, model_path, iteration=-1):
        its = [int(d.split("_")[-1]) for d in os.listdir(os.path.join(model_path, "app_model"))]
        it = max(its) if iteration == -1 else iteration
        self.load_state_dict(torch.load(os.path.join(model_path, f"app_model/iteration_{it}/app.pth")))
'''

# their train.py's setup, as far as state goes (both commits)
_TRAIN_SETUP = '''
import argparse, atexit, json, os, random
from random import randint
import numpy as np
import torch
from scene import GaussianModel
from scene.app_model import AppModel

random.seed(22); np.random.seed(22); torch.manual_seed(22)
ap = argparse.ArgumentParser()
ap.add_argument("-m"); ap.add_argument("--iterations", type=int); ap.add_argument("--log")
ap.add_argument("--checkpoint_iterations", nargs="+", type=int, default=[])
ap.add_argument("--start_checkpoint", default=None)
a = ap.parse_args()
MESH_FROM, DENSIFY_UNTIL = 12, 40
cams = torch.tensor([[3.0, 0, 0], [-3, 0, 0], [0, 3, 0], [0, -3, 0], [0, 0, 3], [0, 0, -3]], dtype=torch.float64)
g = GaussianModel()
g.create(40)
random.random(); np.random.rand(5); torch.rand(5)  # the setup draws numbers (their create_from_mesh does)
g.training_setup()
app = AppModel()
first = 0
if a.start_checkpoint:
    params, first = torch.load(a.start_checkpoint)  # as theirs: torch's default, weights only
    g.restore(params, None)
    app.load_weights(a.m)
stack, log = None, []


@atexit.register  # also when the launcher ends the process at a checkpoint
def write_log():
    with open(a.log, "a") as f:
        f.write(json.dumps({"log": log, "xyz": g.get_xyz.detach().tolist(), "app": app.w.detach().tolist()}) + "\\n")
'''

# the mesh stage's loop (train.py:92-660 of pgsr_dpsr)
_TRAIN = _TRAIN_SETUP + '''
observe = torch.zeros(g.get_xyz.shape[0], dtype=torch.bool)
for it in range(first + 1, a.iterations + 1):
    g.update_learning_rate(it)
    if it % 10 == 1:
        g.decay_view_dir_stats(0.5)
    if not stack:
        stack = list(range(len(cams)))
    cam = stack.pop(randint(0, len(stack) - 1))
    x = g.get_xyz
    vis = ((x.detach() * cams[cam]).sum(1) > -0.5) & (torch.rand(x.shape[0]) > 0.7)  # a few splats a view
    if observe.shape[0] != x.shape[0]:
        observe = torch.zeros(x.shape[0], dtype=torch.bool)
    g.add_view_dir_stat(cams[cam], vis)
    observe |= vis
    loss = ((x - 0.3 * g.normals()) ** 2).sum() + ((app.w - 1) * torch.randn(3, dtype=torch.float64)).sum() ** 2
    loss = loss + 0.01 * (float(np.random.rand()) * x[:, 0].sum() + random.random() * x[:, 1].sum())
    if it > MESH_FROM:
        pts = g.extract_oriented_pointcloud(visibility_mask=observe > 0)
        if len(pts):
            loss = loss + ((x - pts.mean(0)) ** 2).sum()
    loss.backward()
    if it % 100 == 0:
        observe.zero_()
    if it > MESH_FROM and it % 10 == 0 and len(pts) >= 5:
        face = pts.detach()[:5]
        g.set_mesh_guidance(face, torch.rand(5) > 0.3, torch.nn.functional.normalize(face, dim=1))
        g.update_mesh_normal_cache()
    g.optimizer.step(); app.optimizer.step()
    g.optimizer.zero_grad(); app.optimizer.zero_grad()
    if it < DENSIFY_UNTIL and it % 10 == 0:
        g.densify()
    log.append([it, cam, float(loss.detach()), len(pts) if it > MESH_FROM else -1])  # the proxy's points
    if it in a.checkpoint_iterations:
        torch.save((g.capture(), it), os.path.join(a.m, f"chkpnt{it}.pth"))
        app.save_weights(a.m, it)
app.save_weights(a.m, a.iterations)
'''

# the warm-up's: the plain-PGSR commit (de24f1a), whose GaussianModel has no view directions, mesh guidance or
# proxy; its appearance model joins after a while, and its multi-view term draws a virtual or a nearest camera
_WARMUP_GAUSSIAN_MODEL = _GAUSSIAN_MODEL + '''

def _plain_init(self):
    self.use_app = False


GaussianModel.__init__ = _plain_init
for _name in ("decay_view_dir_stats", "add_view_dir_stat", "extract_oriented_pointcloud", "set_mesh_guidance",
              "update_mesh_normal_cache", "normals"):
    delattr(GaussianModel, _name)
'''
_WARMUP_TRAIN = _TRAIN_SETUP + '''
for it in range(first + 1, a.iterations + 1):
    g.update_learning_rate(it)
    if not stack:
        stack = list(range(len(cams)))
    cam = stack.pop(randint(0, len(stack) - 1))
    g.use_app = it > 20
    x = g.get_xyz
    near = cams[(cam + 1) % len(cams)] if np.random.random() < 0.5 else -cams[cam]
    loss = ((x - 0.1 * cams[cam]) ** 2).sum() + random.random() * ((x - 0.05 * near) ** 2).sum()
    if g.use_app:
        loss = loss + ((app.w - 1) * torch.randn(3, dtype=torch.float64)).sum() ** 2
    loss.backward()
    g.optimizer.step(); app.optimizer.step()
    g.optimizer.zero_grad(); app.optimizer.zero_grad()
    if it < DENSIFY_UNTIL and it % 10 == 0:
        g.densify()
    log.append([it, cam, float(loss.detach())])
    if it in a.checkpoint_iterations:
        torch.save((g.capture(), it), os.path.join(a.m, f"chkpnt{it}.pth"))
        app.save_weights(a.m, it)
app.save_weights(a.m, a.iterations)
'''


def _checkout(root, gaussian_model, train):
    (root / "scene").mkdir(parents=True)
    (root / "scene" / "__init__.py").write_text("from scene.gaussian_model import GaussianModel\n")
    (root / "scene" / "gaussian_model.py").write_text(gaussian_model)
    (root / "scene" / "app_model.py").write_text(_APP_MODEL)
    (root / "train.py").write_text(train)
    return root


@pytest.fixture(scope="module")
def checkout(tmp_path_factory):
    return _checkout(tmp_path_factory.mktemp("split") / "checkout", _GAUSSIAN_MODEL, _TRAIN)


def _train(checkout, model, log, *args, launcher=True, **env):
    os.makedirs(model, exist_ok=True)
    cmd = [sys.executable, os.path.join(PEERS, "_peak.py"), str(model / "peak.json")]
    cmd += [os.path.join(PEERS, "_pgsr_split.py")] if launcher else []
    cmd += ["train.py", "-m", str(model), "--iterations", "240", "--log", str(log), *args]
    subprocess.run(cmd, cwd=checkout, check=True, env={**os.environ, **{k: str(v) for k, v in env.items()}})


def _parts(log):
    return [json.loads(line) for line in log.read_text().splitlines()]


def _split_run(checkout, tmp, at, **resume_env):
    model, log = tmp / "model", tmp / "log.jsonl"
    _train(checkout, model, log, "--checkpoint_iterations", str(at), PGSR_SPLIT_STOP=at)
    times = tmp / "times.json"
    env = {"PGSR_SPLIT_STATE": model / f"chkpnt{at}_state.pth", "PGSR_SPLIT_TIMES": times, **resume_env}
    _train(checkout, model, log, "--start_checkpoint", str(model / f"chkpnt{at}.pth"),
           **{k: v for k, v in env.items() if v is not None})
    return _parts(log), times


@pytest.fixture(scope="module")
def whole(checkout, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("whole")
    log = tmp / "whole.jsonl"
    _train(checkout, tmp / "whole", log, launcher=False)
    (part,) = _parts(log)
    return part


# while the splat count still changes; two iterations after train.py cleared its seen mask; long after
@pytest.mark.parametrize("at", [30, 102, 198])
def test_a_stopped_and_resumed_mesh_stage_trains_as_the_uninterrupted_one(checkout, tmp_path, whole, at):
    (first, second), times = _split_run(checkout, tmp_path, at)
    assert [r[0] for r in first["log"]] == list(range(1, at + 1))  # the first part stopped at its checkpoint
    assert first["log"] + second["log"] == whole["log"]  # the same cameras, losses and seen splats, iteration by it.
    assert second["xyz"] == whole["xyz"] and second["app"] == whole["app"]
    t = json.loads(times.read_text())  # the restart's setup, which run_pgsr.py counts once
    assert t["setup_s"] > 0 and t["first_iteration_at"] > 1e9


def test_a_mesh_stage_in_three_parts_trains_as_the_uninterrupted_one(checkout, tmp_path, whole):
    """The middle part resumes and stops again: what it saves holds what it was given back and what it saw."""
    model, log = tmp_path / "model", tmp_path / "log.jsonl"
    _train(checkout, model, log, "--checkpoint_iterations", "108", PGSR_SPLIT_STOP=108)
    for start, stop in ((108, 198), (198, None)):  # after the splat count last changed (30)
        more = ["--checkpoint_iterations", str(stop)] if stop else []
        env = {"PGSR_SPLIT_STOP": stop} if stop else {}
        _train(checkout, model, log, "--start_checkpoint", str(model / f"chkpnt{start}.pth"), *more,
               PGSR_SPLIT_STATE=model / f"chkpnt{start}_state.pth", **env)
    parts = _parts(log)
    assert [len(p["log"]) for p in parts] == [108, 90, 42]
    assert sum((p["log"] for p in parts), []) == whole["log"] and parts[-1]["xyz"] == whole["xyz"]


def test_without_the_saved_state_the_resumed_run_differs(checkout, tmp_path, whole):
    # (the launcher lets their torch.load read the NumPy scalars only on a resume with the state: here by hand)
    (first, second), _ = _split_run(checkout, tmp_path, 198, PGSR_SPLIT_STATE=None,
                                    TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1)
    assert first["log"] + second["log"] != whole["log"]
    # and a split between two refills of the camera stack changes the order of the views: run_pgsr.py refuses it
    (tmp_path / "b").mkdir()
    (first, second), _ = _split_run(checkout, tmp_path / "b", 196)
    assert first["log"] + second["log"] != whole["log"]


def test_the_launcher_leaves_an_unsplit_run_as_it_was(checkout, tmp_path, whole):
    log = tmp_path / "plain.jsonl"
    _train(checkout, tmp_path / "plain", log)
    assert _parts(log) == [whole]


def test_their_checkpoint_needs_more_than_torch_s_weights_only_load(checkout, tmp_path):
    """Their ``train.py`` loads its checkpoint with torch's default: weights only, which refuses the NumPy scalars
    it holds; the launcher's resume lifts that (a resume without it fails as theirs would on torch 2.6 or later)."""
    model, log = tmp_path / "model", tmp_path / "log.jsonl"
    _train(checkout, model, log, "--checkpoint_iterations", "30", PGSR_SPLIT_STOP=30)
    env = {k: v for k, v in os.environ.items() if k != "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"}
    cmd = [sys.executable, "train.py", "-m", str(model), "--iterations", "40", "--log", str(log),
           "--start_checkpoint", str(model / "chkpnt30.pth")]
    run = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    assert run.returncode != 0 and "Weights only load failed" in run.stderr


def test_a_stop_after_some_time_checkpoints_at_a_multiple_of_the_views(checkout, tmp_path, whole):
    """``PGSR_SPLIT_STOP_AFTER``: the launcher writes the checkpoint itself, at the first multiple of the views
    after the time (at once here: 6, the first multiple trained), and the resume trains as the uninterrupted run;
    a time longer than the training leaves it to the end, with no stop recorded."""
    model, log, times = tmp_path / "model", tmp_path / "log.jsonl", tmp_path / "times.json"
    _train(checkout, model, log, PGSR_SPLIT_STOP_AFTER=0, PGSR_SPLIT_VIEWS=6, PGSR_SPLIT_TIMES=times)
    assert json.loads(times.read_text())["stopped_at"] == 6
    _train(checkout, model, log, "--start_checkpoint", str(model / "chkpnt6.pth"),
           PGSR_SPLIT_STATE=model / "chkpnt6_state.pth", PGSR_SPLIT_STOP_AFTER=3600, PGSR_SPLIT_VIEWS=6,
           PGSR_SPLIT_TIMES=times)
    first, second = _parts(log)
    assert len(first["log"]) == 6 and first["log"] + second["log"] == whole["log"] and second["xyz"] == whole["xyz"]
    assert "stopped_at" not in json.loads(times.read_text())


@pytest.fixture(scope="module")
def warmup_checkout(tmp_path_factory):
    return _checkout(tmp_path_factory.mktemp("split") / "warmup", _WARMUP_GAUSSIAN_MODEL, _WARMUP_TRAIN)


@pytest.mark.parametrize("at", [30, 198])
def test_a_stopped_and_resumed_warmup_trains_as_the_uninterrupted_one(warmup_checkout, tmp_path, at):
    """The warm-up's ``train.py`` (the plain-PGSR commit's) under the same launcher: what its classes lack is neither
    patched nor saved, and the restart trains as the uninterrupted run; without the state beside the checkpoint
    (the random states, the appearance model's optimizer) it does not."""
    log = tmp_path / "whole.jsonl"
    _train(warmup_checkout, tmp_path / "whole", log, launcher=False)
    (whole,) = _parts(log)
    (first, second), _ = _split_run(warmup_checkout, tmp_path, at)
    assert first["log"] + second["log"] == whole["log"] and second["xyz"] == whole["xyz"]
    assert second["app"] == whole["app"]
    state = torch.load(tmp_path / "model" / f"chkpnt{at}_state.pth", weights_only=False)
    assert state["gaussians"] == {} and state["seen"] is None
    (tmp_path / "bare").mkdir()
    (first, second), _ = _split_run(warmup_checkout, tmp_path / "bare", at, PGSR_SPLIT_STATE=None,
                                    TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1)
    assert first["log"] + second["log"] != whole["log"]
