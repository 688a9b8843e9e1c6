# SPDX-License-Identifier: Apache-2.0
"""The final fusion of a fit at other grids, truncations and face-support tolerances, from the same rendered depths
(#59: DTU's scene mesh is rough and speckled at the CUDA plan's voxel of 0.8 pixel footprints, smooth at the CPU plan's
2.6; lab/fusion_fp.py). Each variant becomes a result folder of its own beside the fit's, so the peers' scorer reads
the ROI F1 (scenes with a truth) and draws pictures (DTU) for every variant of one fit.

    SCENE_FUSION="K:T:F[,K:T:F...]" python3 lab/device/patched_run.py EXCH OUT [run_wtopo.py's arguments]

K: the voxel as a multiple of the plan's (2: twice as coarse); T: truncation in voxels (the product's 4); F: the face
rule's tolerance in voxels (the product's 2); T and F scale with the voxel in world units. ``install()`` wraps the fit
loop's ``final_mesh`` to fuse every variant after the product's own mesh (render_depths once), and ``_api._finish`` to
write them, in the caller's frame, as ``OUT/run/mesh_fusion_K_T_F.ply``; lab/device/patched_run.py then writes
``OUT_fusion_K_T_F`` (the fit's renders and run.json, that mesh). The variants' fusions run inside the fit's timed span:
the times of a patched fit are not the product's.
"""

import dataclasses
import json
import os
import shutil

from wtopo.fitting import _api, _final_mesh, loop

_meshes: dict = {}
# the fit's training cameras, rendered (depths, colours) and each variant's "mesh_policy" record, for a lab script
last: dict = {}


def variants() -> list[tuple[float, float, float]]:
    spec = os.environ.get("SCENE_FUSION", "")
    return [tuple(float(x) for x in v.split(":")) for v in spec.split(",") if v.strip()]


def _name(k: float, t: float, f: float) -> str:
    return f"fusion_{k:g}_{t:g}_{f:g}"


def install() -> None:
    real, finish = _final_mesh.final_mesh, _api._finish

    def fused(surfels, cameras, cfg, **kw):
        mesh = real(surfels, cameras, cfg, **kw)
        # what is installed now (another lab patch's render_depths or truncation), used and put back as it was
        saved = (_final_mesh.render_depths, _final_mesh.TRUNCATION_VOXELS, _final_mesh._FACE_SUPPORT_VOXELS)
        render_depths, own = saved[0], kw["render"]
        depths = render_depths(own, surfels, cameras)
        _meshes.clear()
        last.clear()
        last.update(cameras=cameras, depths=depths)
        try:
            # the fit's own renderer reads the depths once; another (a chunked merge's unmasked views) renders
            _final_mesh.render_depths = lambda r, *a: depths if r is own else render_depths(r, *a)
            for k, t, f in variants():
                _final_mesh.TRUNCATION_VOXELS, _final_mesh._FACE_SUPPORT_VOXELS = t, f
                res = max(16, int(round(int(cfg.final.resolution) / k)))
                c = dataclasses.replace(cfg, final=dataclasses.replace(cfg.final, resolution=res))
                events = {}
                _meshes[_name(k, t, f)] = real(surfels, cameras, c, **{
                    **kw, "tsdf_info": {}, "record": lambda e, ev=events, **info: ev.__setitem__(e, info)})
                last.setdefault("policy", {})[_name(k, t, f)] = events.get("mesh_policy", {})
        finally:
            _final_mesh.render_depths, _final_mesh.TRUNCATION_VOXELS, _final_mesh._FACE_SUPPORT_VOXELS = saved
        return mesh

    def kept_finish(run, mesh_int, scene, out_dir):
        if out_dir is not None:
            os.makedirs(out_dir, exist_ok=True)
            for name, m in _meshes.items():
                run.sim.to_world(m).export(os.path.join(out_dir, f"mesh_{name}.ply"))
                if os.path.basename(os.path.normpath(out_dir)) == "run":  # run_wtopo.py's OUT/run: the variant's
                    # result folder exists before OUT's run.json, so that a waiting script waits for it too
                    os.makedirs(f"{os.path.dirname(os.path.abspath(out_dir))}_{name}", exist_ok=True)
        _meshes.clear()
        return finish(run, mesh_int, scene, out_dir)

    loop.final_mesh, _api._finish = fused, kept_finish


def write_results(out: str) -> list[str]:
    """A result folder ``OUT_fusion_K_T_F`` per variant beside the fit's ``out`` (its renders, run.json under the
    system name "... (fusion K T F)", the variant's mesh), run.json last and renamed into place."""
    out = os.path.abspath(out)
    with open(os.path.join(out, "run.json")) as f:
        run = json.load(f)
    made = []
    for k, t, f in variants():
        name = _name(k, t, f)
        src = os.path.join(out, "run", f"mesh_{name}.ply")
        if not os.path.exists(src):
            continue
        dst = f"{out.rstrip('/')}_{name}"
        os.makedirs(dst, exist_ok=True)
        shutil.copy(src, os.path.join(dst, "mesh.ply"))
        shutil.copy(os.path.join(out, "renders.npz"), os.path.join(dst, "renders.npz"))
        r = dict(run, system=f"{run.get('system', 'wtopo')} (fusion: voxel x{k:g}, truncation {t:g}, faces {f:g})")
        with open(os.path.join(dst, ".run.json.tmp"), "w") as fh:
            json.dump(r, fh, indent=1)
        os.replace(os.path.join(dst, ".run.json.tmp"), os.path.join(dst, "run.json"))
        made.append(dst)
    return made
