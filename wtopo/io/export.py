# SPDX-License-Identifier: Apache-2.0
"""``wtopo export``: convert a run's USD timeline to a mesh, a 3DGS surfel PLY, or another USD encoding."""

from __future__ import annotations

import os

from ._common import atomic_write
from .ply import export_mesh, write_surfels_ply
from .usd import mesh_at, read_surfels, read_timeline

__all__ = ["export", "EXPORT_FORMATS"]

EXPORT_FORMATS = ("mesh", "surfels", "usda", "usdc")
"""``mesh``: PLY / OBJ / STL / GLB / OFF by suffix; ``surfels``: 3DGS PLY; ``usda`` / ``usdc``: the timeline."""

_MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".off")


def _infer_format(out: str) -> str:
    ext = os.path.splitext(out)[1].lower()
    if ext in (".usda", ".usdc"):
        return ext[1:]
    if ext in _MESH_SUFFIXES:
        return "mesh"
    raise ValueError(f"cannot infer the export format from {out!r}: pass fmt, one of {list(EXPORT_FORMATS)}")


def export(run_dir: str | os.PathLike, out: str | os.PathLike, fmt: str | None = None, *,
           iteration: int | None = None) -> str:
    """Export a run (a directory holding ``timeline.usdc``, or the timeline file itself).

    Args:
        run_dir: run directory or USD timeline path.
        out: output path.
        fmt: one of :data:`EXPORT_FORMATS`; ``None`` infers it from the suffix (``.ply`` means a
            mesh; pass ``"surfels"`` for a 3DGS PLY).
        iteration: for ``mesh`` / ``surfels``, the latest sample at or before this iteration;
            ``None`` exports the static ``final`` mesh when the timeline has one, else the last
            sample.

    Returns:
        ``out`` as a string.

    Raises:
        FileNotFoundError: no timeline.
        ValueError: unknown ``fmt``, a suffix that does not fit it, or nothing to export.
    """
    src = os.fspath(run_dir)
    if os.path.isdir(src):
        src = os.path.join(src, "timeline.usdc")
    if not os.path.exists(src):
        raise FileNotFoundError(f"no USD timeline at {src}")
    out = os.fspath(out)
    fmt = _infer_format(out) if fmt is None else fmt
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"fmt must be one of {list(EXPORT_FORMATS)}, got {fmt!r}")
    ext = os.path.splitext(out)[1].lower()
    if fmt == "mesh":
        tl = read_timeline(src)
        mesh = tl.meshes["final"] if iteration is None and "final" in tl.meshes else mesh_at(tl, iteration)
        return export_mesh(mesh, out)
    if fmt == "surfels":
        if ext != ".ply":
            raise ValueError(f"surfels export writes a .ply file, got {out!r}")
        s = read_surfels(src, iteration)
        return write_surfels_ply(out, s.means, s.quats, s.scales, s.opacities, s.sh)
    if ext != "." + fmt:
        raise ValueError(f"fmt {fmt!r} needs an output ending in .{fmt}, got {out!r}")
    from pxr import Sdf

    layer = Sdf.Layer.OpenAsAnonymous(src)

    def write(tmp: str) -> None:
        if not layer.Export(tmp):
            raise OSError(f"Sdf.Layer.Export failed writing {tmp}")

    return atomic_write(out, write, suffix=ext)
