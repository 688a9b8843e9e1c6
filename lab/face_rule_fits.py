"""Lab (nothing imports it): a built-in scene fitted twice on the CPU, with the scene mesh's per-face view-support
rule (geometry.mesh_policy.supported_faces) and without it, scored by the fit's own Chamfer / F-score against the
scene's ground truth: what the rule does on a scene it was not tuned on (bunny_room: the bunny in a textured room).

    PYTHONPATH=. .venv/bin/python lab/face_rule_fits.py [SCENE] [--preset balanced]
"""
import argparse
import json

import wtopo
from wtopo import scenes
from wtopo.fitting import _final_mesh as F
from wtopo.fitting.config import FitConfig


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", nargs="?", default="bunny_room")
    ap.add_argument("--preset", default="balanced")
    a = ap.parse_args()
    rule = F.supported_faces
    for label, fn in (("with the rule", rule), ("without", lambda mesh, *args, **kw: (mesh, {}))):
        F.supported_faces = fn
        cfg = FitConfig()
        cfg.preset = a.preset
        cfg.runtime.device = "cpu"
        cfg.runtime.usd_every = 0
        res = wtopo.fit(scenes.load(a.scene), cfg, progress=False)
        rep = res.report
        ev = [e for e in rep.get("events", []) if e.get("event") == "mesh_policy"]
        print(json.dumps({"scene": a.scene, "rule": label, "chamfer_pct": 100 * rep.get("chamfer", float("nan")),
                          "f_score": rep.get("f_score"), "accuracy": rep.get("accuracy"),
                          "completeness": rep.get("completeness"), "faces": rep["mesh"]["faces"],
                          "face_rule": ev[-1].get("faces") if ev else None}), flush=True)
    F.supported_faces = rule


if __name__ == "__main__":
    main()
