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
import importlib.util
import os
import sys

__version__ = "0.1.0"


def _mount_kernels() -> None:
    # Installed, ``kernels/`` is the package ``wtopo.kernels`` (pyproject package-dir).  Run from a
    # source tree (``PYTHONPATH=.``) it is not, so mount the folder under that name.
    if "wtopo.kernels" in sys.modules or importlib.util.find_spec("wtopo.kernels") is not None:
        return
    src = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "kernels", "__init__.py")
    if os.path.exists(src):
        spec = importlib.util.spec_from_file_location("wtopo.kernels", src,
                                                      submodule_search_locations=[os.path.dirname(src)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules["wtopo.kernels"] = mod
        spec.loader.exec_module(mod)


_mount_kernels()

import warp as _wp  # noqa: E402

_wp.config.quiet = True  # no greeting
if hasattr(_wp, "LOG_WARNING") and _wp.config.log_level < _wp.LOG_WARNING:
    _wp.config.log_level = _wp.LOG_WARNING  # no module-load timings; warnings and errors still show

from .camera import Camera  # noqa: E402

_LAZY = {
    "Scene": ("wtopo.scene", "Scene"),
    "load_scene": ("wtopo.loaders", "load_scene"),
    "fit": ("wtopo.fit", "fit"),
    "FitConfig": ("wtopo.fit", "FitConfig"),
    "FitResult": ("wtopo.fit", "FitResult"),
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
