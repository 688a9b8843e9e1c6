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

# Warp's global configuration is set here and nowhere else. Warp 1.19 (pinned) gates its greeting
# and module-load timings on the log level (``config.quiet`` is gone); warnings and errors still show.
if _wp.config.log_level < _wp.LOG_WARNING:
    _wp.config.log_level = _wp.LOG_WARNING

# The line Warp's native library prints (fprintf to stderr, no config option silences it) when it
# finds no CUDA driver: on a CPU-only machine that is the expected state, not a warning.
_CUDA_PROBE_LINE = ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. "
                    "GPU execution will not be available.")


def _init_warp(init=_wp.init) -> None:
    """Run Warp's ``init`` with its no-CUDA-driver line removed from stderr; every other line it
    prints (real warnings and errors) is written back to ``sys.stderr``.

    The native library writes to file descriptor 2 directly, so the descriptor is pointed at a
    temporary file for the call. Where there is no descriptor 2 to redirect (some embedded
    interpreters), ``init`` runs as is.
    """
    import os
    import sys
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # closed or missing stderr: nothing to filter
        init()
        return
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            lines = captured.read().decode(errors="replace").splitlines(keepends=True)
            kept = "".join(ln for ln in lines if ln.rstrip("\r\n") != _CUDA_PROBE_LINE)
            if kept:
                sys.stderr.write(kept)
                sys.stderr.flush()


# Initialise now, once, so that no later implicit ``wp.init()`` (the first launch or allocation)
# prints the probe line; ~30 ms on CPU.
_init_warp()

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
