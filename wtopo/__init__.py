# SPDX-License-Identifier: Apache-2.0
"""wtopo: posed photographs to a watertight mesh.

Gaussian surfels are fitted to the images while a differentiable proxy mesh is rebuilt from them
every iteration (oriented points -> trilinear scatter -> FFT Poisson -> marching cubes -> BVH ray
casting); every hot operation is an NVIDIA Warp kernel that runs on CPU and CUDA.

Public entry points: :class:`Camera`, :class:`Scene`, :func:`load_scene`, :func:`fit`,
:class:`FitConfig`, and the modules :mod:`wtopo.ops`, :mod:`wtopo.scenes`, :mod:`wtopo.metrics`,
:mod:`wtopo.io`.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"


import warp as _wp  # noqa: E402

_wp.config.quiet = True  # no greeting
if hasattr(_wp, "LOG_WARNING") and _wp.config.log_level < _wp.LOG_WARNING:
    _wp.config.log_level = _wp.LOG_WARNING  # no module-load timings; warnings and errors still show

from .camera import Camera  # noqa: E402

_LAZY = {
    "Scene": ("wtopo.scene", "Scene"),
    "load_scene": ("wtopo.loaders", "load_scene"),
    "fit": ("wtopo.fitting", "fit"),
    "FitConfig": ("wtopo.fitting", "FitConfig"),
    "FitResult": ("wtopo.fitting", "FitResult"),
    "ops": ("wtopo.ops", None),
    "scenes": ("wtopo.scenes", None),
    "metrics": ("wtopo.metrics", None),
    "io": ("wtopo.io", None),
}

__all__ = ["Camera", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        mod, attr = _LAZY[name]
        m = importlib.import_module(mod)
        return m if attr is None else getattr(m, attr)
    raise AttributeError(f"module 'wtopo' has no attribute {name!r}")
