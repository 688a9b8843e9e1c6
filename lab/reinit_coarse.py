"""A/B: the TSDF re-initialisation without Open3D (a lab script: nothing imports it).

    python lab/reinit_coarse.py SCENE PRESET VARIANT

VARIANT: base (shipped: the fusion and the quadric decimation to the planned faces); coarse (where the fused
mesh has more than the planned faces, fused again at a voxel grown by sqrt(faces / planned), so no decimation
runs); coarse90 (the same, aiming at 90 % of the planned faces). Its A/B of the Open3D fusion and decimation
against Warp's and fast_simplification's (decisions.md) ran at the commit before they went.
Prints one JSON line: fit seconds, re-init seconds, faces of the re-init mesh, Chamfer, F, PSNR."""
import json
import math
import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks"))
import error_vs_runtime as E  # noqa: E402

import wtopo  # noqa: E402
from wtopo.fitting import _reinit as R  # noqa: E402
from wtopo.fitting.config import FitConfig  # noqa: E402
from wtopo.fitting.tsdf import FusionBounds  # noqa: E402

LOG = {}


def main():
    scene_name, preset, variant = sys.argv[1:4]
    cfg = FitConfig()
    cfg.preset = preset
    cfg.runtime.device = "cpu"
    if variant.startswith("coarse"):
        aim = 0.9 if variant == "coarse90" else 1.0
        real = R.fuse_depths

        def fuse(cams, depths, colors, bounds, **kw):
            mesh = real(cams, depths, colors, bounds, **kw)
            cap = R_cfg["max_faces"]
            LOG["first_faces"] = len(mesh.faces)
            if len(mesh.faces) > cap:
                g = math.sqrt(len(mesh.faces) / (aim * cap))
                b = FusionBounds(bounds.lower, bounds.upper, bounds.voxel * g, bounds.truncation * g)
                mesh = real(cams, depths, colors, b, **kw)
            LOG["faces"] = len(mesh.faces)
            return mesh

        R.fuse_depths = fuse
    R_cfg = {}
    real_reinit = R.tsdf_reinit

    def reinit(surfels, cameras, c, **kw):
        R_cfg["max_faces"] = c.tsdf.max_faces
        out = real_reinit(surfels, cameras, c, **kw)
        LOG["reinit_faces"] = out.info.get("reinit_faces")
        return out

    R.tsdf_reinit = reinit
    import wtopo.fitting.stages as St  # the loop imports tsdf_reinit by name: patch where it is looked up
    for mod in list(sys.modules.values()):
        if getattr(mod, "tsdf_reinit", None) is real_reinit and mod is not R:
            mod.tsdf_reinit = reinit
    del St
    scene = E.load_scene(scene_name)
    with tempfile.TemporaryDirectory() as out:
        res = wtopo.fit(scene, cfg, out_dir=out, progress=False)
        rep = res.report
    st = rep["stage_times_s"]
    print(json.dumps({"scene": scene_name, "preset": preset, "variant": variant, "fit_s": rep["elapsed_s"],
                      "tsdf_s": round(st.get("tsdf", 0), 2), **LOG, "chamfer": rep.get("chamfer"),
                      "f": rep.get("f_score"), "psnr": rep.get("psnr")}))


if __name__ == "__main__":
    main()
