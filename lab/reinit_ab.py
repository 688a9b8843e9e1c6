"""A/B of the TSDF re-initialisation's cost on the CPU presets (a lab script: nothing imports it).

    python lab/reinit_ab.py SCENE PRESET VARIANT

VARIANT: base (shipped), sample (mesh_to_surfels draws faces by area instead of Open3D's quadric decimation),
resN (tsdf.resolution N; res128: the value before the plan chose it), sample+resN.
Prints one JSON line: fit seconds, re-init seconds, Chamfer, F."""
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks"))
import error_vs_runtime as E  # noqa: E402

import wtopo  # noqa: E402
from wtopo.fitting import tsdf as T  # noqa: E402
from wtopo.fitting.config import FitConfig  # noqa: E402


def main():
    scene_name, preset, variant = sys.argv[1:4]
    if variant.startswith("sample"):
        import types

        real = T.importlib.util.find_spec  # only tsdf.py's view of importlib: the fusion still uses Open3D
        T.importlib = types.SimpleNamespace(util=types.SimpleNamespace(
            find_spec=lambda name, *a: None if name == "open3d" else real(name, *a)))
    cfg = FitConfig()
    cfg.preset = preset
    cfg.runtime.device = "cpu"
    if "res" in variant:
        cfg.tsdf.resolution = int(variant.split("res")[1])
    scene = E.load_scene(scene_name)
    with tempfile.TemporaryDirectory() as out:
        res = wtopo.fit(scene, cfg, out_dir=out, progress=False)
        rep = res.report
    st = rep["stage_times_s"]
    print(json.dumps({"scene": scene_name, "preset": preset, "variant": variant, "fit_s": rep["elapsed_s"],
                      "tsdf_s": round(st.get("tsdf", 0), 2), "chamfer": rep.get("chamfer"),
                      "f": rep.get("f_score"), "psnr": rep.get("psnr")}))


if __name__ == "__main__":
    main()
