# SPDX-License-Identifier: Apache-2.0
"""The fit pipeline behind :func:`wtopo.fit`.

The public surface is what this package exports (``__all__``): for users :func:`fit`,
:class:`FitConfig` (nested stage configs, their enums) and :class:`FitResult`; for the code that drives
fits (:mod:`wtopo.chunks`, the CLI) :func:`fit_surfels`, :func:`validate_config`, the plan
(:func:`make_plan`, :func:`resolve_config`, :func:`iteration_budget`, :func:`plan_defaults`) and the
pieces of the final meshing (:class:`Renderer`, :func:`final_mesh`, :class:`ProxyMesh`, :class:`Timers`,
:func:`near_distance`). Everything else is internal; modules whose name starts with ``_`` are private.

Modules:

* ``_api``: :func:`fit`, posed images in, a watertight mesh in the caller's frame out; :func:`fit_surfels`;
* ``config``: :class:`FitConfig`, a keyword-only dataclass of nested stage configs;
* ``validate_config``: checks a configuration before the fit does any work;
* ``plan``: the stage plan, which parts of the fit a scene needs, each with its reason;
* ``_defaults``: the plan's base budgets on a kind of device (:func:`plan_defaults`);
* ``scene_kind``: what kind of capture a scene is and where its region of interest lies;
* ``_init_surfels``: stage 1, the initial surfels from the scene's points or the cameras' common volume;
* ``surfels``: the surfel parameter container (parameters, Adam groups, prune / clone / split);
* ``background``: surfels for the background of unmasked captures, kept at distance;
* ``loop``: the fit loop, :class:`~.loop.FitRun` driving warm-up, TSDF re-initialisation,
  co-evolution and the final mesh;
* ``stages``: the stage names, the renderer every stage renders through and its depth maps;
* ``_reinit``: the TSDF re-initialisation stage;
* ``_final_mesh``: the final mesh (fusion, meshing policy, watertight re-mesh);
* ``_strategy``: density control as one strategy object with per-iteration hooks;
* ``objective``: which loss terms apply in an iteration, with which weight, on which pixels;
* ``losses``: the loss terms, pure torch and finite for any rendered input;
* ``densify``: screen-space clone / split, opacity prune and reset, and the mesh-guided steps;
* ``proxy``: the differentiable proxy mesh (oriented points, Poisson, marching cubes, ray cast);
* ``tsdf``: TSDF fusion of rendered surfel depth (Open3D, or the Warp kernel of :mod:`wtopo.tsdf_fusion`)
  and the TSDF re-initialisation;
* ``evaluate``: history records (losses, timings; Chamfer / F-score / PSNR given a ground truth);
* ``checkpoint``: atomic, validated, resumable checkpoint files;
* ``checkpointing``: when checkpoints of a running fit are written and how a fit resumes;
* ``_timeline``: the USD timeline of a fit (cameras, surfels, proxy mesh, final mesh);
* ``profiling``: the fit's section timers and the ``runtime.profile`` time table per stage;
* ``_progress``: what a running fit shows (tqdm bars) and how it is stopped (SIGINT / SIGTERM).

The geometry the fit shares with the rest of the package (stereo, lens warp, winding, meshing policy,
region of interest) is :mod:`wtopo.geometry`.
"""

from ._api import FitResult, fit, fit_surfels
from ._defaults import PlanDefaults, plan_defaults
from ._final_mesh import final_mesh
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
    PolishConfig,
    Preset,
    RemovedFieldError,
    RuntimeConfig,
    TSDFConfig,
    WarmupConfig,
)
from .loop import FitAborted
from .plan import Plan, iteration_budget, make_plan, resolve_config
from .profiling import Timers
from .proxy import ProxyMesh
from .scene_kind import SceneKind, near_distance
from .stages import Renderer
from .surfels import Surfels
from .validate_config import validate_config

__all__ = [
    "fit", "FitResult", "FitConfig", "FitAborted", "Plan", "Surfels", "InitConfig", "OptimConfig", "WarmupConfig",
    "TSDFConfig", "CoevolutionConfig", "PolishConfig", "FinalConfig", "DensifyConfig", "LossConfig", "MeshConfig",
    "RuntimeConfig", "NormalFlip", "DepthLoss", "InitSource", "PoissonBox", "Preset",
    "SceneKind", "RemovedFieldError",
    # for the code that drives fits (wtopo.chunks, the CLI)
    "fit_surfels", "validate_config", "make_plan", "resolve_config", "iteration_budget", "PlanDefaults",
    "plan_defaults", "Renderer", "final_mesh", "ProxyMesh", "Timers", "near_distance",
]

