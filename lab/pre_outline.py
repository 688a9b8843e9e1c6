# SPDX-License-Identifier: Apache-2.0
"""Keep the final mesh as it was before the outline offset (#59): both meshes of one fit, so that the offset's gain
on a GPU, where two fits of one scene differ by several per cent, is measured without the run-to-run spread.

    KEEP_PRE_OUTLINE=1 python3 lab/device/patched_run.py EXCH OUT [run_wtopo.py's arguments]

``install()`` wraps ``_final_mesh._outline`` to remember the mesh it was given and ``_api._finish`` to write that
mesh, in the caller's frame, as ``OUT/run/mesh_pre_outline.ply``; lab/device/patched_run.py then writes the result
folder ``OUT_pre`` beside ``OUT`` (the same renders and times, that mesh). A fit whose outline step did not make its
final mesh writes its final mesh there (the two folders then score alike). The file's export is inside the fit's
timed span (a second or less).
"""

import json
import os
import shutil

from wtopo.fitting import _api, _final_mesh

FILE = "mesh_pre_outline.ply"
_kept = {}


def install() -> None:
    outline, finish = _final_mesh._outline, _api._finish

    def kept_outline(mesh, *args, **kwargs):
        out = outline(mesh, *args, **kwargs)
        _kept.update(mesh=mesh, out=out)
        return out

    def kept_finish(run, mesh_int, scene, out_dir):
        # the mesh the outline step was given, only when this fit's outline step made its final mesh (a fit that
        # raised after it leaves a stale entry; a fit resumed after its mesh, or without masks, runs no outline step)
        pre = _kept["mesh"] if _kept.get("out") is mesh_int else mesh_int
        _kept.clear()
        if out_dir is not None:
            os.makedirs(out_dir, exist_ok=True)
            if os.path.basename(os.path.normpath(out_dir)) == "run":  # run_wtopo.py's OUT/run: patched_run.py's
                # result folder OUT_pre exists before OUT's run.json, so that a waiting script waits for both
                os.makedirs(_pre_folder(os.path.dirname(os.path.abspath(out_dir))), exist_ok=True)
            run.sim.to_world(pre).export(os.path.join(out_dir, FILE))
        return finish(run, mesh_int, scene, out_dir)

    _final_mesh._outline, _api._finish = kept_outline, kept_finish


def _pre_folder(out: str) -> str:
    return out.rstrip("/") + "_pre"


def write_result(out: str) -> str:
    """The result folder ``OUT_pre`` beside the fit's ``out``: its renders, its run.json under the system name
    "... (before the outline offset)", ``run/mesh_pre_outline.ply`` as ``mesh.ply``; run.json last and renamed
    into place, so that a waiting script (lab/device/wait_fits.sh) never scores a half-written folder."""
    out = os.path.abspath(out)
    dst = _pre_folder(out)
    os.makedirs(dst, exist_ok=True)
    shutil.copy(os.path.join(out, "run", FILE), os.path.join(dst, "mesh.ply"))
    shutil.copy(os.path.join(out, "renders.npz"), os.path.join(dst, "renders.npz"))
    with open(os.path.join(out, "run.json")) as f:
        run = json.load(f)
    run["system"] = run.get("system", "wtopo") + " (before the outline offset)"
    with open(os.path.join(dst, ".run.json.tmp"), "w") as f:
        json.dump(run, f, indent=1)
    os.replace(os.path.join(dst, ".run.json.tmp"), os.path.join(dst, "run.json"))
    return dst
