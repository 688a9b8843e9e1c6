# SPDX-License-Identifier: Apache-2.0
"""The fit pipeline behind :func:`wtopo.fit`.

Exports :func:`fit`, :class:`FitConfig` (nested stage configs) and :class:`FitResult`.

Modules:

* ``api``: :func:`fit`, posed images in, a watertight mesh in the caller's frame out;
* ``config``: :class:`FitConfig`, a keyword-only dataclass of nested stage configs;
* ``validate_config``: checks a configuration before the fit does any work;
* ``plan``: the stage plan, which parts of the fit a scene needs, each with its reason;
* ``scene_kind``: what kind of capture a scene is and where its region of interest lies;
* ``init``: stage 1, the initial surfels from the scene's points or the cameras' common volume;
* ``surfels``: the surfel parameter container (parameters, Adam groups, prune / clone / split);
* ``background``: surfels for the background of unmasked captures, kept at distance;
* ``loop``: the fit loop, :class:`~.loop.FitRun` driving warm-up, TSDF re-initialisation,
  co-evolution and the final mesh;
* ``stages``: the discrete stages around the loop (TSDF re-initialisation, final mesh);
* ``strategy``: density control as one strategy object with per-iteration hooks;
* ``objective``: which loss terms apply in an iteration, with which weight, on which pixels;
* ``losses``: the loss terms, pure torch and finite for any rendered input;
* ``densify``: screen-space clone / split, opacity prune and reset, and the mesh-guided steps;
* ``proxy``: the differentiable proxy mesh (oriented points, Poisson, marching cubes, ray cast);
* ``tsdf``: TSDF fusion of rendered surfel depth (Open3D, or the Warp kernel of :mod:`wtopo.tsdf_fusion`)
  and the TSDF re-initialisation;
* ``depth_warp``: resampling a lens camera's depth and colour onto an ideal pinhole camera;
* ``mesh_policy``: what the returned mesh keeps (which components, by view support);
* ``evaluate``: history records (losses, timings; Chamfer / F-score / PSNR given a ground truth);
* ``checkpoint``: atomic, validated, resumable checkpoint files;
* ``checkpointing``: when checkpoints of a running fit are written and how a fit resumes;
* ``timeline``: the USD timeline of a fit (cameras, surfels, proxy mesh, final mesh);
* ``profiling``: the fit's section timers and the ``runtime.profile`` time table per stage;
* ``progress``: what a running fit shows (tqdm bars) and how it is stopped (SIGINT / SIGTERM).
"""

from .api import FitResult, fit
from .config import (
    CoevolutionConfig,
    DensifyConfig,
    DepthLoss,
    FinalConfig,
    FitConfig,
    InitConfig,
    InitSource,
    LossConfig,
    MeshConfig,
    NormalFlip,
    OptimConfig,
    PoissonBox,
    RemovedFieldError,
    RuntimeConfig,
    TSDFBackend,
    TSDFConfig,
    WarmupConfig,
)
from .loop import FitAborted
from .plan import Plan
from .scene_kind import SceneKind
from .surfels import Surfels

__all__ = [
    "fit", "FitResult", "FitConfig", "FitAborted", "Plan", "Surfels", "InitConfig", "OptimConfig", "WarmupConfig",
    "TSDFConfig", "CoevolutionConfig", "FinalConfig", "DensifyConfig", "LossConfig", "MeshConfig",
    "RuntimeConfig", "NormalFlip", "DepthLoss", "InitSource", "PoissonBox", "TSDFBackend",
    "SceneKind", "RemovedFieldError",
]

