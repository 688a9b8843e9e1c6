# SPDX-License-Identifier: Apache-2.0
"""The scene mesh policy's host time on a large fused mesh, against the trimesh operations it replaced.

A DTU-sized final mesh (two icospheres of 1.3M faces each, 2.6M faces) and 40 views of 369 x 370 ray-cast
depth maps; timed in one process, each step beside the trimesh operation it replaced:

* component labels: :func:`wtopo.geometry.components.face_components` (SciPy on the vertex graph) against
  ``trimesh.graph.connected_component_labels(mesh.face_adjacency)``;
* faces near a camera: :func:`wtopo.geometry.mesh_policy.crop_near_cameras` (the cameras within ``near`` of the
  mesh's box, then a k-d tree over them) against its previous form, its per-face pass over every camera
  (``_crop_near``), with the cameras all away from the mesh (a region of interest's final mesh, DTU's) and with
  one within ``near`` of it;
* the clean-up: without merging vertices by position (a marching-cubes mesh shares them already) against
  ``Trimesh.merge_vertices``;
* the support rules' projections (every vertex into every view): :func:`wtopo.vertex_support.view_agreement` (a
  Warp kernel) on ``--device`` against their NumPy formulation (``tests/reference/vertex_support.py``), and
  :func:`~wtopo.geometry.mesh_policy.supported_components` and :func:`~wtopo.geometry.mesh_policy.supported_faces`
  on ``--device``; with ``--against FILE`` (another version of ``wtopo/geometry/mesh_policy.py``, e.g. ``git show
  e77081a:wtopo/geometry/mesh_policy.py``: NumPy on the CPU, torch on CUDA) beside that version's rules;
* an object's repair (:func:`wtopo.fitting.tsdf.repair_mesh`, the same mesh with 50 faces removed) against the
  same steps on trimesh's ``is_watertight``, ``fill_holes`` first and ``fix_inversion`` (mass properties).

    .venv/bin/python benchmarks/bench_mesh_policy.py [--subdivisions 8] [--device cpu] [--against FILE]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import trimesh
from _from_tests import load, load_file  # beside this script

from wtopo import Camera
from wtopo.fitting.tsdf import _FAN_MAX_EDGES, cleanup_mesh, fill_boundary_loops, repair_mesh
from wtopo.geometry.components import face_components
from wtopo.geometry.mesh_policy import (
    _crop_near,
    _face_areas,
    crop_near_cameras,
    keep_faces,
    supported_components,
    supported_faces,
)
from wtopo.geometry.winding import orient_faces
from wtopo.ops import raycast_mesh
from wtopo.vertex_support import view_agreement


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def _repair_with_trimesh(mesh):
    """The repair as it was: trimesh's closedness tests, its hole filling first, its inversion fix."""
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    if not mesh.is_watertight:
        fill_boundary_loops(mesh, _FAN_MAX_EDGES)
    mesh.faces = orient_faces(mesh.faces)
    trimesh.repair.fix_inversion(mesh)
    return mesh


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subdivisions", type=int, default=8)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                    help="torch device of the support rules' projections")
    ap.add_argument("--against", default=None, help="another version of wtopo/geometry/mesh_policy.py")
    a = ap.parse_args(argv)
    sphere = trimesh.creation.icosphere(subdivisions=a.subdivisions)
    other = sphere.copy()
    other.apply_translation([2.5, 0.0, 0.0])
    mesh = trimesh.util.concatenate([sphere, other])
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    cams = []
    for k in range(40):
        ang = 2 * np.pi * k / 40
        eye = np.array([1.25 + 5 * np.cos(ang), 5 * np.sin(ang), 1.0])
        cams.append(Camera.look_at(eye, np.array([1.25, 0, 0]), np.array([0, 0, 1.0]), fov_x=0.9, width=369,
                                   height=370))
    r = raycast_mesh(torch.as_tensor(mesh.vertices, dtype=torch.float32),
                     torch.as_tensor(mesh.faces, dtype=torch.int32), cams)
    depths = [np.where(m, d, 0) for m, d in zip(r.mask.numpy(), r.depth.numpy())]
    centers = np.array([c.center for c in cams])
    rows = []
    t_new, _ = _timed(lambda: face_components(np.asarray(mesh.faces), len(mesh.vertices)))
    t_old, _ = _timed(lambda: trimesh.graph.connected_component_labels(
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).face_adjacency, node_count=len(mesh.faces)))
    rows.append(("component labels", t_new, t_old))
    t_new, (_, n_new) = _timed(lambda: crop_near_cameras(mesh, centers, 0.1))
    t_old, (_, n_old) = _timed(lambda: _crop_near(mesh, centers, 0.1))
    assert n_new == n_old
    rows.append(("faces near a camera, none near the mesh (old: every face)", t_new, t_old))
    one = np.concatenate([centers, [[0.0, 0.0, 1.05]]])  # above the first sphere's pole, within 0.1 of it
    t_new, (_, n_new) = _timed(lambda: crop_near_cameras(mesh, one, 0.1))
    t_old, (_, n_old) = _timed(lambda: _crop_near(mesh, one, 0.1))
    assert n_new == n_old > 0
    rows.append(("faces near a camera, one near the mesh (old: every face)", t_new, t_old))
    t_new, _ = _timed(lambda: cleanup_mesh(mesh, largest_component=False, repair=False, weld=False))
    t_old, _ = _timed(lambda: cleanup_mesh(mesh, largest_component=False, repair=False, weld=True))
    rows.append(("clean-up (old: merge vertices by position)", t_new, t_old))
    # the rules' projections (every vertex into every view): the kernel on --device against the NumPy formulation
    view_agreement_numpy = load("reference/vertex_support.py").view_agreement_numpy
    verts = np.asarray(mesh.vertices)
    vt = torch.as_tensor(verts, dtype=torch.float64, device=a.device)
    every = torch.arange(len(verts), device=a.device)
    dt = [torch.as_tensor(d, device=a.device) for d in depths]
    view_agreement(vt, every, cams[0], dt[0])  # the kernel's first launch loads (or builds) its module
    t_old, _ = _timed(lambda: [view_agreement_numpy(verts, c, d) for c, d in zip(cams, depths)])
    t_new, _ = _timed(lambda: [view_agreement(vt, every, c, d).sum().item() for c, d in zip(cams, dt)])
    rows.append((f"support projections, kernel on {a.device} (old: NumPy)", t_new, t_old))
    old = load_file(a.against, "wtopo.geometry._mesh_policy_against") if a.against else None
    old_dev = a.device if torch.device(a.device).type == "cuda" else None
    tol = 2.0 * 2.5 / 512  # the fit's: two fusion voxels of a 512-voxel box around both spheres
    for name, new_fn, old_fn in (
            ("supported components", lambda: supported_components(mesh, cams, depths, device=a.device),
             lambda: old.supported_components(mesh, cams, depths, device=old_dev)),
            ("supported faces", lambda: supported_faces(mesh, cams, depths, tol, device=a.device),
             lambda: old.supported_faces(mesh, cams, depths, tol, device=old_dev))):
        t_new, out = _timed(new_fn)
        t_old = None
        if old is not None:
            t_old, ref = _timed(old_fn)
            assert out[1] == ref[1] and np.array_equal(out[0].faces, ref[0].faces), f"{name}: another result"
        rows.append((f"{name} on {a.device}" + (" (old: --against)" if old else ""), t_new, t_old))
    keep = np.random.default_rng(1).random(len(mesh.faces)) < 0.9

    def _trimesh_keep():
        out = mesh.copy()
        out.update_faces(keep)
        out.remove_unreferenced_vertices()
        return out.area_faces

    t_new, _ = _timed(lambda: _face_areas(keep_faces(mesh, keep)))
    t_old, _ = _timed(_trimesh_keep)
    rows.append(("keep 90 % of the faces, with areas (old: trimesh's copy)", t_new, t_old))
    holed = np.asarray(mesh.faces)[np.setdiff1d(np.arange(len(mesh.faces)),
                                                np.random.default_rng(0).choice(len(mesh.faces), 50, replace=False))]
    t_new, _ = _timed(lambda: repair_mesh(trimesh.Trimesh(mesh.vertices, holed, process=False)))
    t_old, _ = _timed(lambda: _repair_with_trimesh(trimesh.Trimesh(mesh.vertices, holed, process=False)))
    rows.append(("an object's repair (50 holes)", t_new, t_old))
    print(f"{len(mesh.faces):,} faces, {len(cams)} views of 369 x 370")
    print(f"{'step':<56} {'wtopo s':>8} {'replaced s':>10} {'ratio':>6}")
    for name, new, old in rows:
        print(f"{name:<56} {new:8.2f} " + (f"{old:10.2f} {new / old:6.2f}" if old else f"{'':>10} {'':>6}"))


if __name__ == "__main__":
    main()
