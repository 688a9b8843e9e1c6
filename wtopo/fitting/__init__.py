# SPDX-License-Identifier: Apache-2.0
"""The fit pipeline behind :func:`wtopo.fit`: :func:`fit`, :class:`FitConfig` (nested stage configs) and :class:`FitResult`.

Modules: ``config`` (settings), ``plan`` (what a scene needs, with reasons), ``surfels`` (the
parameter container), ``losses``, ``densify`` (density control and mesh guidance), ``tsdf``
(Open3D fusion and re-initialisation), ``proxy`` (the differentiable proxy mesh), ``checkpoint``
(atomic, resumable), ``loop`` (the stages) and ``api`` (:func:`fit`).
"""

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

