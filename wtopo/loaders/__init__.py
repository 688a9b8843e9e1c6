# SPDX-License-Identifier: Apache-2.0
"""Dataset readers: :func:`load_scene` detects the format of a folder and returns a
:class:`wtopo.Scene` in the dataset's own world frame and units.

Formats (field names and axis conventions in each loader's module docstring): Blender / NeRF-synthetic
``transforms_{train,val,test}.json``; COLMAP ``sparse/0`` (text or binary); DTU
``cameras_sphere.npz`` / ``cameras.npz`` (IDR / NeuS layout); nerfstudio ``transforms.json``.
"""

from __future__ import annotations

import os

from .blender import load_blender, write_blender
from .colmap import find_colmap_model, load_colmap
from .dtu import load_dtu
from .nerfstudio import load_nerfstudio

__all__ = ["load_scene", "detect_format", "load_blender", "write_blender", "load_colmap", "load_dtu",
           "load_nerfstudio"]

_LOADERS = {"blender": load_blender, "colmap": load_colmap, "dtu": load_dtu, "nerfstudio": load_nerfstudio}


def detect_format(path: str) -> str:
    """``"blender"``, ``"nerfstudio"``, ``"dtu"`` or ``"colmap"`` for a dataset folder (or a
    ``transforms*.json`` / ``cameras*.npz`` file)."""
    p = os.fspath(path)
    if os.path.isfile(p):
        base = os.path.basename(p)
        if base == "transforms.json":
            return "nerfstudio"
        if base.startswith("transforms_") and base.endswith(".json"):
            return "blender"
        if base.endswith(".npz"):
            return "dtu"
        raise ValueError(f"cannot tell the dataset format of file {p}; pass its folder")
    if not os.path.isdir(p):
        raise FileNotFoundError(f"dataset path does not exist: {p}")
    if any(os.path.isfile(os.path.join(p, f"transforms_{s}.json")) for s in ("train", "val", "test")):
        return "blender"
    if os.path.isfile(os.path.join(p, "transforms.json")):
        return "nerfstudio"
    if any(os.path.isfile(os.path.join(p, f)) for f in ("cameras_sphere.npz", "cameras.npz")):
        return "dtu"
    if find_colmap_model(p) is not None:
        return "colmap"
    raise ValueError(f"{p} holds no known dataset: looked for transforms_{{train,val,test}}.json (Blender), "
                     "transforms.json (nerfstudio), cameras_sphere.npz / cameras.npz (DTU) and "
                     "cameras.{bin,txt} in ., sparse/0 or sparse (COLMAP)")


def load_scene(path, *, format: str | None = None, **kwargs):
    """Read a dataset into a :class:`wtopo.Scene`.

    Args:
        path: dataset folder (or its ``transforms*.json`` / ``cameras*.npz``).
        format: force ``"blender"``, ``"colmap"``, ``"dtu"`` or ``"nerfstudio"`` instead of detecting.
        **kwargs: passed to the reader (``background``, ``downscale``, and per-format options).

    Raises:
        ValueError: unknown format, unsupported camera model, bad cameras (naming the camera index).
    """
    p = os.fspath(path)
    fmt = format or detect_format(p)
    if fmt not in _LOADERS:
        raise ValueError(f"format must be one of {sorted(_LOADERS)}, got {format!r}")
    if os.path.isfile(p) and fmt in ("blender", "dtu"):
        if fmt == "dtu":
            kwargs.setdefault("cameras_file", os.path.basename(p))
        p = os.path.dirname(p) or "."
    return _LOADERS[fmt](p, **kwargs)
