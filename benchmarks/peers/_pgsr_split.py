# SPDX-License-Identifier: Apache-2.0
"""Run ``pgsr_dpsr``'s ``train.py`` so that a stage can stop at a checkpoint and go on from it in another process,
on another machine (``run_pgsr.py --stop-at`` / ``--resume``: the published 30,000 + 10,000 iterations do not fit
one device lease). The mesh stage runs the newest commit's ``train.py``; the warm-up (``--no-mesh-stage``) the
plain-PGSR commit's, which has the same loop, checkpoint and appearance model without the mesh stage's view
directions, mesh guidance and proxy: what a class lacks is neither saved nor patched.

python _pgsr_split.py [NEXT_LAUNCHER] train.py ARGS...   (in the checkout, under ``_peak.py``)

Environment:

* ``PGSR_SPLIT_STOP=N`` ends the process once the checkpoint of iteration N is written (with
  ``--checkpoint_iterations N``);
* ``PGSR_SPLIT_STOP_AFTER=SECONDS`` with ``PGSR_SPLIT_VIEWS=K`` ends it at the first iteration N, a multiple of K,
  that ends SECONDS or more after this launcher's start, writing the checkpoint there as ``train.py``'s own would
  be (a lease's time is known, the loop's rate less so);
* ``PGSR_SPLIT_STATE=PATH`` puts back the state saved beside the checkpoint that ``--start_checkpoint`` restores;
* ``PGSR_SPLIT_TIMES=PATH`` receives the time of the first training iteration's start (``first_iteration_at``,
  seconds since the epoch; the launcher that started the process subtracts its start: the setup a restart
  repeats), the seconds to it from this launcher's start (``setup_s``) and, when the process stops at a
  checkpoint, its iteration (``stopped_at``).

Their checkpoint (``chkpntN.pth``: ``GaussianModel.capture()``; ``app_model/iteration_N``) holds the splats, their
optimizer state and densification statistics. Their ``train.py`` carries more from one iteration to the next,
which this launcher writes beside the checkpoint (``chkpntN_state.pth``, atomically) and puts back:

* ``GaussianModel`` attributes outside ``capture()``: the per-splat view-direction sums, the mesh guidance (face
  centroids, visibility and normals) and each splat's cached guidance normal and its reliability;
* which splats a training view has seen since ``train.py`` last cleared its local ``observe_count`` (whose mask
  selects the points of the DPSR proxy; cleared after every 100th iteration and when the splat count changes):
  tracked here by the same rules, and after the restart OR-ed into the mask passed to
  ``extract_oriented_pointcloud`` until the next clearing, so the mask is the uninterrupted run's;
* the appearance model's optimizer state (its weights are in their checkpoint);
* the random states of Python, NumPy and torch (CPU and every CUDA device), put back at the first iteration after
  the restart, after the setup has drawn its own numbers.

A resume also lets their ``train.py``'s ``torch.load`` of its own checkpoint read it whole
(``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD``): it holds NumPy scalars (the scene scale, the schedule's learning rate),
which torch's default weights-only loading refuses.

The camera order is not state: ``train.py`` draws views from a shuffled stack that it refills when empty, so a
split at a multiple of the number of training views finds the stack empty in both runs (``run_pgsr.py`` refuses
other iterations). With that, the restarted run draws the same numbers as the uninterrupted one; GPU kernels that
sum in varying order still differ from run to run, as they do between two uninterrupted runs.
"""

from __future__ import annotations

import json
import os
import random
import runpy
import sys
import time

import numpy as np
import torch

OBSERVE_CLEARED_EVERY = 100  # their train.py: ``if iteration % 100 == 0: observe_count.zero_()`` after backward
_GM_STATE = ("view_dir_accumulation", "mesh_guidance_cached_normals", "mesh_guidance_cached_reliable",
             "mesh_guidance_face_centroids", "mesh_guidance_face_visible", "mesh_guidance_face_normals")


def _rng_state() -> dict:
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def _set_rng_state(s: dict) -> None:
    random.setstate(s["python"])
    np.random.set_state(s["numpy"])
    torch.set_rng_state(s["torch"])
    if s["cuda"]:
        torch.cuda.set_rng_state_all(s["cuda"])


def _save(obj, path: str) -> None:
    """``torch.save`` whole or not at all: a process ended mid-write leaves no half file under ``path``."""
    torch.save(obj, path + ".part")
    os.replace(path + ".part", path)


def install(gaussian_model, app_model, *, stop_at: int | None = None, state: str | None = None,
            times: str | None = None, t0: float | None = None, stop_after: float | None = None,
            views: int | None = None, model_path: str | None = None) -> None:
    """Patch the classes of the modules ``gaussian_model`` (the checkout's ``scene.gaussian_model``) and
    ``app_model`` (``scene.app_model``) in place; the arguments are the environment's (module docstring)."""
    GM, App = gaussian_model.GaussianModel, app_model.AppModel
    if getattr(GM, "_split_installed", False):
        return
    t0 = time.perf_counter() if t0 is None else t0
    live: dict = {"stop_at": stop_at}  # the models train.py trains, what a restart put back, where to stop
    pending: dict = {}
    if stop_after is not None and not (views and model_path):
        raise ValueError("_pgsr_split: a stop after some time needs the views' number and the model path")

    capture, restore, update_lr = GM.capture, GM.restore, GM.update_learning_rate
    # the mesh stage's alone (the warm-up's GaussianModel has neither)
    add_stat, extract = getattr(GM, "add_view_dir_stat", None), getattr(GM, "extract_oriented_pointcloud", None)
    save_weights, load_weights, app_init = App.save_weights, App.load_weights, App.__init__

    # live["seen"], what a restart put back, is dropped when train.py would clear its mask (p_add_view_dir_stat,
    # p_update_learning_rate): while it is there it has the splat count's shape
    def seen_now(g):
        """The splats seen since train.py last cleared its mask: tracked here, and what a restart put back."""
        seen, back = getattr(g, "_split_seen", None), live.get("seen")
        return seen if back is None or seen is None else seen | back

    def p_capture(self):
        live["g"] = self
        return capture(self)

    def p_add_view_dir_stat(self, cam_center, visibility_filter):
        out = add_stat(self, cam_center, visibility_filter)
        n = self.get_xyz.shape[0]
        seen = getattr(self, "_split_seen", None)
        if seen is None or seen.shape[0] != n:  # train.py resets observe_count so, before this call
            seen = torch.zeros((n,), dtype=torch.bool, device=visibility_filter.device)
            if live.get("seen") is not None and live["seen"].shape[0] != n:
                live["seen"] = None  # the count changed since the restart: theirs starts afresh too
        self._split_seen = seen | visibility_filter
        return out

    def p_extract(self, *args, **kwargs):
        mask, back = kwargs.get("visibility_mask"), live.get("seen")
        if mask is not None and back is not None:
            kwargs["visibility_mask"] = mask | back
        return extract(self, *args, **kwargs)

    def write_times(**more):
        if times:
            live["times"] = {**live.get("times", {}), **more}
            with open(times, "w") as f:
                json.dump(live["times"], f)

    def p_update_learning_rate(self, iteration):
        if iteration % OBSERVE_CLEARED_EVERY == 1:  # train.py cleared its observe_count after the last iteration
            self._split_seen = None
            live["seen"] = None
        live.setdefault("first", iteration)
        done = iteration - 1  # the state now is the state at the end of that iteration
        if (stop_after is not None and done >= live["first"] and done % views == 0
                and time.perf_counter() - t0 >= stop_after):
            live["stop_at"], live["g"] = done, self
            _save((capture(self), done), os.path.join(model_path, f"chkpnt{done}.pth"))  # as train.py's own
            live["app"].save_weights(model_path, done)  # then the state beside it, and the process ends
        if "rng" in pending:  # the first iteration after a restart: the setup has drawn its numbers by now
            _set_rng_state(pending.pop("rng"))
        if "setup" not in live:
            live["setup"] = time.perf_counter() - t0
            write_times(first_iteration_at=time.time(), setup_s=live["setup"])
        return update_lr(self, iteration)

    def p_save_weights(self, model_path, iteration):
        save_weights(self, model_path, iteration)
        ckpt = os.path.join(model_path, f"chkpnt{iteration}.pth")
        if "g" not in live or not os.path.isfile(ckpt):
            return  # the end of training, not a checkpoint
        g = live["g"]
        # (at a multiple of 100 train.py has just cleared its own: the restart's first iteration clears this one)
        blob = {"iteration": int(iteration), "gaussians": {k: getattr(g, k) for k in _GM_STATE if hasattr(g, k)},
                "seen": seen_now(g), "app_optimizer": self.optimizer.state_dict(), "rng": _rng_state()}
        _save(blob, os.path.join(model_path, f"chkpnt{iteration}_state.pth"))
        if live["stop_at"] is not None and int(iteration) == live["stop_at"]:
            write_times(stopped_at=int(iteration))
            print(f"\n[_pgsr_split] stopped after the checkpoint of iteration {iteration}", flush=True)
            sys.exit(0)

    def p_restore(self, model_args, training_args):
        restore(self, model_args, training_args)
        live["g"] = self
        if state:
            blob = torch.load(state, map_location="cpu", weights_only=False)
            dev = self._xyz.device
            for k, v in blob["gaussians"].items():
                setattr(self, k, v.to(dev) if torch.is_tensor(v) else v)
            live["seen"] = None if blob["seen"] is None else blob["seen"].to(dev)
            pending["rng"], pending["app_optimizer"] = blob["rng"], blob["app_optimizer"]

    def p_app_init(self, *args, **kwargs):
        app_init(self, *args, **kwargs)
        live["app"] = self

    def p_load_weights(self, model_path, iteration=-1):
        load_weights(self, model_path, iteration)
        if "app_optimizer" in pending:
            self.optimizer.load_state_dict(pending.pop("app_optimizer"))

    GM.capture, GM.restore, GM.update_learning_rate = p_capture, p_restore, p_update_learning_rate
    if add_stat is not None:
        GM.add_view_dir_stat = p_add_view_dir_stat
    if extract is not None:
        GM.extract_oriented_pointcloud = p_extract
    App.save_weights, App.load_weights, App.__init__ = p_save_weights, p_load_weights, p_app_init
    GM._split_installed = True


if __name__ == "__main__":
    start = time.perf_counter()
    sys.argv = sys.argv[1:]
    from scene import app_model as _app  # the checkout, first on the path (``_peak.py``)
    from scene import gaussian_model as _gm

    stop, after = os.environ.get("PGSR_SPLIT_STOP"), os.environ.get("PGSR_SPLIT_STOP_AFTER")
    model = None  # train.py's model folder: its parser keeps the last -m / --model_path
    for i, w in enumerate(sys.argv):
        if w in ("-m", "--model_path") and i + 1 < len(sys.argv):
            model = sys.argv[i + 1]
        elif w.startswith("--model_path="):
            model = w.split("=", 1)[1]
    if os.environ.get("PGSR_SPLIT_STATE"):  # their checkpoint holds NumPy scalars: torch.load must read it whole
        os.environ["TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD"] = "1"
    install(_gm, _app, stop_at=int(stop) if stop else None, state=os.environ.get("PGSR_SPLIT_STATE") or None,
            times=os.environ.get("PGSR_SPLIT_TIMES") or None, t0=start,
            stop_after=float(after) if after else None, views=int(os.environ.get("PGSR_SPLIT_VIEWS") or 0),
            model_path=model)
    runpy.run_path(sys.argv[0], run_name="__main__")
