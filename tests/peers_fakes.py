# SPDX-License-Identifier: Apache-2.0
"""For the peers benchmark's tests: a small exchange folder, and ``run_pgsr``'s children (the authors' ``train.py``,
``render.py`` and the held-out renders) stood in for, without their code or a GPU."""

from __future__ import annotations

import os
import sys

import numpy as np

PEERS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "peers")
if PEERS not in sys.path:
    sys.path.insert(0, PEERS)


def small_exchange(tmp_path_factory):
    """A small exchange folder (``exchange.load``'s): the bunny, 16 views of 48 px, every fourth held out."""
    from exchange import export, load

    from wtopo import scenes

    root = str(tmp_path_factory.mktemp("exch") / "bunny16")
    scene = scenes.load("bunny", n_views=16, resolution=48)
    scene.name = "bunny16"
    export(scene, root, test_every=4, n_points=500)
    return load(root)


def fake_pgsr(monkeypatch, calls, mesh_scale=1.0):
    """``run_pgsr``'s children stood in for: each records its folder, command and environment in ``calls``; training
    and meshing record their peak, meshing writes
    a TSDF mesh (a box, scaled to tell runs apart), the held-out renders write ``views.npz``."""
    import json
    import time

    import run_pgsr
    import trimesh

    def run(cmd, cwd, log, **env):
        calls.append((os.path.basename(cwd), cmd, env))
        if "_peak.py" in os.path.basename(cmd[1]):
            script = next(c for c in cmd[3:] if c in ("train.py", "render.py"))  # after the launchers
            with open(cmd[2], "w") as f:
                json.dump({"peak_gpu_bytes": 1000 if script == "train.py" else 10}, f)
            # _pgsr_split.py: --stop-at's iteration, or --stop-after's (two rounds of the views if the time is short)
            it = env.get("PGSR_SPLIT_STOP")
            if "PGSR_SPLIT_STOP_AFTER" in env and float(env["PGSR_SPLIT_STOP_AFTER"]) < 100:
                it = str(2 * int(env["PGSR_SPLIT_VIEWS"]))
            if it:  # its checkpoint and the state beside it
                model = cmd[cmd.index("-m") + 1]
                os.makedirs(os.path.join(model, "app_model", f"iteration_{it}"), exist_ok=True)
                for name in (f"chkpnt{it}.pth", f"chkpnt{it}_state.pth", f"app_model/iteration_{it}/app.pth"):
                    open(os.path.join(model, name), "w").close()
            if "PGSR_SPLIT_TIMES" in env:  # as if its first iteration began 0.25 s after now
                with open(env["PGSR_SPLIT_TIMES"], "w") as f:
                    json.dump({"first_iteration_at": time.time() + 0.25, "setup_s": 0.2,
                               **({"stopped_at": int(it)} if it else {})}, f)
            if script == "render.py":
                mesh = os.path.join(cmd[cmd.index("-m") + 1], "mesh")
                os.makedirs(mesh, exist_ok=True)
                trimesh.creation.box(extents=[mesh_scale] * 3).export(os.path.join(mesh, "tsdf_fusion_post.ply"))
        else:  # _peer_views.py pgsr MODEL IT EXCHANGE VIEWS
            np.savez(cmd[-1], rgb=np.zeros((1, 4, 4, 3), np.float16), n=7, peak=20)

    monkeypatch.setattr(run_pgsr, "_run", run)
    return run_pgsr
