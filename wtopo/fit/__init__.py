# SPDX-License-Identifier: Apache-2.0
"""The fit pipeline: :func:`fit`, :class:`FitConfig` (nested stage configs) and :class:`FitResult`.

Modules: ``config`` (settings), ``plan`` (what a scene needs, with reasons), ``surfels`` (the
parameter container), ``losses``, ``densify`` (density control and mesh guidance), ``tsdf``
(Open3D fusion and re-initialisation), ``proxy`` (the differentiable proxy mesh), ``checkpoint``
(atomic, resumable), ``loop`` (the stages) and ``api`` (:func:`fit`).
"""

import sys
import types

from .api import FitResult, fit
from .config import (
    CoevolutionConfig,
    DensifyConfig,
    DepthLoss,
    FinalConfig,
    FitConfig,
    InitConfig,
    LossConfig,
    MeshConfig,
    NormalFlip,
    OptimConfig,
    RuntimeConfig,
    TSDFConfig,
    WarmupConfig,
)
from .loop import FitAborted
from .plan import Plan
from .surfels import Surfels

__all__ = [
    "fit", "FitResult", "FitConfig", "FitAborted", "Plan", "Surfels", "InitConfig", "OptimConfig", "WarmupConfig",
    "TSDFConfig", "CoevolutionConfig", "FinalConfig", "DensifyConfig", "LossConfig", "MeshConfig",
    "RuntimeConfig", "NormalFlip", "DepthLoss",
]


class _CallableModule(types.ModuleType):
    """``wtopo.fit`` is both this package and the function: importing the package binds the
    attribute ``wtopo.fit`` to the module, so the module forwards calls to :func:`fit`."""

    def __call__(self, *args, **kwargs):
        return fit(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
