# SPDX-License-Identifier: Apache-2.0
"""Dataset readers: :func:`load_scene` detects the format of a folder and returns a
:class:`wtopo.Scene` in the dataset's own world frame and units.

Formats (field names and axis conventions in each loader's module docstring): Blender / NeRF-synthetic
``transforms_{train,val,test}.json``; COLMAP ``sparse/0`` (text or binary); DTU
``cameras_sphere.npz`` / ``cameras.npz`` (IDR / NeuS layout); nerfstudio ``transforms.json``; a
folder of photographs without cameras (``"photos"``: poses from structure from motion with
pycolmap, :mod:`wtopo.loaders.sfm`, written as ``sparse/0`` beside the images and read back as COLMAP).
"""

from __future__ import annotations

import os

from .blender import load_blender, write_blender
from .colmap import find_colmap_model, load_colmap
from .dtu import load_dtu
from .nerfstudio import load_nerfstudio
from .sfm import SFM_SUMMARY, SfMError, SfMOptions, find_photos, load_photos, run_sfm

__all__ = ["load_scene", "detect_format", "load_blender", "write_blender", "load_colmap", "load_dtu",
           "load_nerfstudio", "load_photos", "run_sfm", "SfMOptions", "SfMError"]

_LOADERS = {"blender": load_blender, "colmap": load_colmap, "dtu": load_dtu, "nerfstudio": load_nerfstudio,
            "photos": load_photos}


def detect_format(path: str) -> str:
    """``"blender"``, ``"nerfstudio"``, ``"dtu"`` or ``"colmap"`` for a dataset folder (or a
    ``transforms*.json`` / ``cameras*.npz`` file); ``"photos"`` for a folder of images (or one
    holding ``images/``) with none of these cameras, or with the COLMAP model :func:`run_sfm` wrote
    there (its ``sfm.json`` beside ``sparse/``)."""
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
        # a model run_sfm made (its sfm.json beside sparse/): load_photos reuses it and undistorts
        # the photos as on the first run
        if os.path.isfile(os.path.join(p, SFM_SUMMARY)) and find_photos(p) is not None:
            return "photos"
        return "colmap"
    if find_photos(p) is not None:
        return "photos"
    raise ValueError(f"{p} holds no known dataset: looked for transforms_{{train,val,test}}.json (Blender), "
                     "transforms.json (nerfstudio), cameras_sphere.npz / cameras.npz (DTU), "
                     "cameras.{bin,txt} in ., sparse/0 or sparse (COLMAP) and image files in ., images/ or image/ "
                     "(photos, posed by structure from motion)")


def load_scene(path, *, format: str | None = None, **kwargs):
    """Read a dataset into a :class:`wtopo.Scene`.

    Args:
        path: dataset folder (or its ``transforms*.json`` / ``cameras*.npz``).
        format: force ``"blender"``, ``"colmap"``, ``"dtu"``, ``"nerfstudio"`` or ``"photos"`` instead
            of detecting (``"photos"`` ignores any cameras the folder has and poses the images by
            structure from motion, reusing its earlier ``sparse/0``).
        **kwargs: passed to the reader (``background``, ``downscale``, and per-format options, e.g.
            ``progress``, ``out_dir`` and ``options`` of :func:`~wtopo.loaders.sfm.load_photos`).

    Raises:
        ValueError: unknown format, unsupported camera model, bad cameras (naming the camera index);
            :class:`~wtopo.loaders.sfm.SfMError` when structure from motion registers too few photos.
        ModuleNotFoundError: ``"photos"`` without pycolmap (the message says ``pip install "wtopo[sfm]"``).
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
