# SPDX-License-Identifier: Apache-2.0
"""TSDF fusion whose contributions behind a view's depth fade out before the truncation (#59: thin parts thickened
by the fusion, design/decisions.md "Open: wtopo's meshes lie inside the surface").

    FUSION_DECAY=1 .venv/bin/python lab/patched_hard.py [lab/hard.py's arguments]
    FUSION_DECAY=2 DECAY_THIN_ONLY=1 ...   the final fusion only, and only where the co-evolution found thin parts
                                           (its "final_grid_thin" event: the finer final grid's rule)
    FUSION_DECAY=1 FUSION_ONLY=1 .venv/bin/python lab/fusion_decay.py chair blob_flat    (the true depths fused)

The fusion (kernels/tsdf_fusion.py) gives every view whose depth lies within the truncation in front of a node
weight 1 (Open3D's rule). Behind a part thinner than the truncation, the views that see its near face then say
"inside" as loudly as the views that see its far face say "outside", and the part thickens: the thin chair's true
depths fused at the CPU plan's grid lie +0.046 % of the diagonal outside. Here a contribution with
``sdf < -FUSION_DECAY`` voxels has weight ``(sdf + truncation) / (truncation - FUSION_DECAY voxels)``, falling
linearly to 0 at the truncation; nodes within FUSION_DECAY voxels behind the surface, which place the zero
crossing, keep weight 1. ``install()`` rewrites the kernel module's source into a temporary file and points the
fusion's wrappers at it (lab/fit_patches.py's FUSION_DECAY).
"""

import importlib.util
import os
import sys
import tempfile

OLD = """                    if sdf > -vol.truncation:
                        total += wp.min(1.0, sdf / vol.truncation)
                        weight += 1.0
                        if use_color != 0:
                            c = color[pix]
                            rgb += wp.vec3(float(c[0]), float(c[1]), float(c[2]))
"""
NEW = """                    if sdf > -vol.truncation:
                        wd = float(1.0)
                        if sdf < -DECAY_VOXELS * vol.voxel:
                            wd = (sdf + vol.truncation) / (vol.truncation - DECAY_VOXELS * vol.voxel)
                        total += wd * wp.min(1.0, sdf / vol.truncation)
                        weight += wd
                        if use_color != 0:
                            c = color[pix]
                            rgb += wd * wp.vec3(float(c[0]), float(c[1]), float(c[2]))
"""


def install() -> float:
    """Point ``wtopo.tsdf_fusion`` at the decaying kernel; returns FUSION_DECAY [voxels]."""
    import wtopo.kernels.tsdf_fusion as k
    import wtopo.tsdf_fusion as tf
    from wtopo.tsdf_fusion import _fusion, _slab

    decay = float(os.environ.get("FUSION_DECAY", "2"))
    with open(k.__file__) as f:
        src = f.read()
    assert src.count(OLD) == 1, "the fusion kernel changed: update lab/fusion_decay.py"
    src = src.replace(OLD, NEW).replace("import warp as wp\n",
                                        f"import warp as wp\n\nDECAY_VOXELS = wp.constant({decay})\n", 1)
    path = os.path.join(tempfile.mkdtemp(prefix="wtopo_decay_"), "tsdf_fusion_decay.py")
    with open(path, "w") as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location("tsdf_fusion_decay", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["tsdf_fusion_decay"] = mod
    spec.loader.exec_module(mod)
    if os.environ.get("DECAY_THIN_ONLY"):
        _install_thin_only(mod, (tf, _fusion, _slab))
    else:
        for m in (tf, _fusion, _slab):
            m._k = mod
    return decay


def _install_thin_only(mod, modules) -> None:
    """The decaying kernel for the final fusion of fits whose co-evolution recorded "final_grid_thin" only."""
    from wtopo.fitting import loop

    final_mesh = loop.final_mesh

    def thin_final_mesh(*args, **kwargs):
        run = kwargs["record"].__self__
        if not any(e["event"] == "final_grid_thin" for e in run.events):
            return final_mesh(*args, **kwargs)
        old = [m._k for m in modules]
        for m in modules:
            m._k = mod
        try:
            return final_mesh(*args, **kwargs)
        finally:
            for m, k in zip(modules, old):
                m._k = k

    loop.final_mesh = thin_final_mesh


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    if os.environ.get("FUSION_DECAY"):
        print(f"fusion decay from {install()} voxels")
    import silhouette_excess

    silhouette_excess.main(sys.argv[1:])
