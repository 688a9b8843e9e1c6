# SPDX-License-Identifier: Apache-2.0
"""Validation of a :class:`~wtopo.fitting.config.FitConfig` before :func:`wtopo.fit` does any work.

One table, :data:`FIELD_CHECKS`, maps the dotted path of every leaf field (``"warmup.iterations"``)
to its check; :func:`validate_config` runs the table, then the cross-field checks. A wrong type
raises :class:`TypeError`, a value out of range :class:`ValueError`; both name the field by its
dotted path and give the bad value, e.g. ``FitConfig.warmup.iterations must be an int >= 0, got -3``.

Type rules: ``bool`` is not an int (nor a number); an ``int`` is accepted where a float is; numbers
must be Python ``int`` / ``float`` (the configuration is JSON-serialised into checkpoints, which a
NumPy ``float32`` or ``int64`` breaks); an enum field takes the member or its string value.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import re
from dataclasses import dataclass
from types import MappingProxyType

from ..rasterize import FILTER_SIGMA_RANGE
from .config import DepthLoss, FitConfig, NormalFlip
from .scene_kind import SceneKind

__all__ = ["FIELD_CHECKS", "validate_config"]

_PREFIX = "FitConfig"
_TSDF_MAX = 2048  # Open3D's TSDF volume is sparse (voxel blocks): 2048 voxels per side is still sane
_POISSON_MAX = 1024  # the Poisson grid is dense (FFT): 1024^3 complex nodes already take 8 GiB per buffer
_GRID_MIN = 8  # coarser Poisson / TSDF grids cannot resolve any shape
_SEED_MAX = 2**32 - 1  # NumPy's default_rng and torch.manual_seed (times 1_000_003) both accept this range
_SH_MAX = 3
_DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")


def _fail(path: str, expect: str, value, *, type_error: bool = False):
    if type_error:
        raise TypeError(f"{path} must be {expect}, got {value!r} ({type(value).__name__})")
    raise ValueError(f"{path} must be {expect}, got {value!r}")


def _interval(lo, hi, lo_open: bool, hi_open: bool) -> str:
    lo, hi = (f"{x:g}" if isinstance(x, float) else x for x in (lo, hi))
    if hi is None:
        return f"{'>' if lo_open else '>='} {lo}"
    return f"in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"


@dataclass(frozen=True)
class _Number:
    """An int (``integer=True``, bool rejected) or a finite int/float within ``[lo, hi]``."""

    integer: bool
    lo: float
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    optional: bool = False

    @property
    def expect(self) -> str:
        kind = "an int" if self.integer else "a finite number"
        none = " or None" if self.optional else ""
        return f"{kind} {_interval(self.lo, self.hi, self.lo_open, self.hi_open)}{none}"

    def __call__(self, path: str, v) -> None:
        if v is None and self.optional:
            return
        if isinstance(v, bool) or not isinstance(v, int if self.integer else (int, float)):
            _fail(path, self.expect, v, type_error=True)
        if isinstance(v, float) and not math.isfinite(v):
            _fail(path, self.expect, v)
        below = v <= self.lo if self.lo_open else v < self.lo
        above = self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi)
        if below or above:
            _fail(path, self.expect, v)


def _int(lo: int, hi: int | None = None, *, optional: bool = False) -> _Number:
    return _Number(True, lo, hi, optional=optional)


def _float(lo: float, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           optional: bool = False) -> _Number:
    return _Number(False, lo, hi, lo_open, hi_open, optional)


_RATE = _float(0.0)  # a learning rate or loss weight: finite and >= 0
_FRACTION = _float(0.0, 1.0)  # a fraction, opacity threshold or weight in [0, 1]
_OPEN_UNIT = _float(0.0, 1.0, lo_open=True, hi_open=True)  # an opacity that goes through a logit
_COUNT = _int(0)  # iterations, intervals where 0 disables, counts
_POSITIVE = _int(1)  # intervals and counts that must be at least 1


@dataclass(frozen=True)
class _Bool:
    """A ``bool`` (``optional``: or ``None``, the plan decides)."""

    optional: bool = False

    @property
    def expect(self) -> str:
        return "a bool or None" if self.optional else "a bool"

    def __call__(self, path: str, v) -> None:
        if not (isinstance(v, bool) or (v is None and self.optional)):
            _fail(path, self.expect, v, type_error=True)


@dataclass(frozen=True)
class _Choice:
    """One of the strings ``values``; with ``enum_type``, a member of that enum too."""

    values: tuple[str, ...]
    enum_type: type[enum.Enum] | None = None
    optional: bool = False

    @property
    def expect(self) -> str:
        names = ", ".join(repr(v) for v in self.values)
        return (f"one of {names}" + (f" (or a {self.enum_type.__name__})" if self.enum_type else "")
                + (" or None" if self.optional else ""))

    def __call__(self, path: str, v) -> None:
        if v is None and self.optional:
            return
        if self.enum_type is not None and isinstance(v, self.enum_type):
            return
        if not isinstance(v, str):
            _fail(path, self.expect, v, type_error=True)
        if v not in self.values:
            _fail(path, self.expect, v)


def _enum(cls: type[enum.Enum], *, optional: bool = False) -> _Choice:
    return _Choice(tuple(m.value for m in cls), cls, optional)


@dataclass(frozen=True)
class _IntChoice:
    """One of the ints ``values``."""

    values: tuple[int, ...]

    @property
    def expect(self) -> str:
        return "an int, one of " + ", ".join(str(v) for v in self.values)

    def __call__(self, path: str, v) -> None:
        if isinstance(v, bool) or not isinstance(v, int):
            _fail(path, self.expect, v, type_error=True)
        if v not in self.values:
            _fail(path, self.expect, v)


@dataclass(frozen=True)
class _Device:
    """``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (a string: the configuration is JSON-serialised)."""

    expect: str = "'auto', 'cpu', 'cuda' or 'cuda:N'"

    def __call__(self, path: str, v) -> None:
        if not isinstance(v, str):
            _fail(path, self.expect, v, type_error=True)
        if not _DEVICE.fullmatch(v):
            _fail(path, self.expect, v)


@dataclass(frozen=True)
class _Colour:
    """``None`` (the scene's, else the plan's) or a tuple/list of 3 finite numbers in [0, 1]."""

    expect: str = "None or a tuple of 3 numbers in [0, 1]"

    def __call__(self, path: str, v) -> None:
        if v is None:
            return
        if not isinstance(v, (tuple, list)):
            _fail(path, self.expect, v, type_error=True)
        if len(v) != 3:
            _fail(path, self.expect, v)
        for i, c in enumerate(v):
            _FRACTION(f"{path}[{i}]", c)


FIELD_CHECKS = MappingProxyType({
    # -- init
    "init.source": _Choice(("auto", "points", "cameras")),
    "init.num_points": _POSITIVE,
    "init.opacity": _OPEN_UNIT,
    "init.scale_neighbours": _POSITIVE,
    "init.background_points": _int(0, optional=True),
    # -- optim (Adam learning rates; cross check: means_final <= means)
    "optim.means": _RATE,
    "optim.means_final": _RATE,
    "optim.quats": _RATE,
    "optim.scales": _RATE,
    "optim.opacities": _RATE,
    "optim.sh_dc": _RATE,
    "optim.sh_rest": _RATE,
    # -- warmup
    "warmup.iterations": _int(0, optional=True),
    # -- tsdf
    "tsdf.enabled": _Bool(),
    "tsdf.resolution": _int(_GRID_MIN, _TSDF_MAX),
    "tsdf.truncation_voxels": _float(0.0, lo_open=True),
    "tsdf.depth": _Choice(("median", "expected")),
    # rendered opacity is <= 1, so a threshold above 1 fuses no pixel: the STABILITY.md case
    # ``tsdf_empty`` (benchmarks/stability.py) sets 1.5 to force the empty-fusion fallback
    "tsdf.alpha_threshold": _RATE,
    "tsdf.max_views": _POSITIVE,
    "tsdf.hybrid_distance": _RATE,
    "tsdf.max_faces": _POSITIVE,
    # -- coevolution
    "coevolution.iterations": _int(0, optional=True),
    "coevolution.mesh_every": _POSITIVE,
    "coevolution.correspondence_every": _POSITIVE,
    "coevolution.enabled": _Bool(),
    # -- final
    "final.method": _Choice(("tsdf", "proxy")),
    "final.resolution": _int(_GRID_MIN, _TSDF_MAX, optional=True),  # also the grid of the watertight Poisson re-mesh
    "final.poisson_resolution": _int(_GRID_MIN, _POISSON_MAX),
    "final.largest_component": _Bool(),
    "final.watertight": _Bool(),
    # -- densify
    "densify.enabled": _Bool(optional=True),
    "densify.start": _COUNT,
    "densify.interval": _POSITIVE,
    "densify.stop_fraction": _float(0.0, 1.0, lo_open=True),
    "densify.grad_threshold": _RATE,
    "densify.max_growth": _FRACTION,  # one clone/split adds at most one surfel per candidate
    "densify.percent_dense": _FRACTION,
    "densify.prune_opacity": _FRACTION,
    "densify.opacity_reset_interval": _COUNT,
    "densify.opacity_reset_value": _OPEN_UNIT,  # clamped through a logit
    "densify.geometry_prune": _Bool(),
    "densify.geometry_prune_distance": _RATE,
    "densify.geometry_prune_opacity": _FRACTION,
    "densify.geometry_densify": _Bool(),
    "densify.geometry_densify_max": _COUNT,
    # -- losses
    "losses.dssim": _FRACTION,
    "losses.mask": _float(0.0, optional=True),
    "losses.normal": _RATE,
    "losses.normal_start": _COUNT,
    "losses.distortion": _RATE,
    "losses.distortion_start": _COUNT,
    "losses.scale": _RATE,
    "losses.max_anisotropy": _float(1.0),  # a ratio max/min of the two scales is >= 1
    "losses.mesh_depth": _RATE,
    "losses.mesh_normal": _RATE,
    "losses.depth_form": _enum(DepthLoss),
    "losses.mesh_depth_source": _Choice(("expected", "median")),
    "losses.silhouette_band": _COUNT,
    # -- mesh
    "mesh.resolution": _int(_GRID_MIN, _POISSON_MAX, optional=True),
    "mesh.sigma": _RATE,
    "mesh.padding": _FRACTION,
    "mesh.samples_per_surfel": _IntChoice((1, 5)),  # centre only, or centre + 4 tangent offsets
    "mesh.offset": _RATE,
    "mesh.offset_weight": _RATE,
    "mesh.normal_flip": _enum(NormalFlip),
    "mesh.flip_distance": _RATE,
    "mesh.opacity_threshold": _FRACTION,
    "mesh.poisson_box": _Choice(("unit", "initial_mesh")),
    "mesh.surface_prior": _RATE,
    # -- runtime
    "runtime.device": _Device(),
    "runtime.seed": _int(0, _SEED_MAX),
    "runtime.max_surfels": _int(1, optional=True),
    "runtime.checkpoint_every": _COUNT,
    "runtime.checkpoint_seconds": _RATE,
    "runtime.keep_checkpoints": _POSITIVE,  # the loop keeps max(2, keep_checkpoints)
    "runtime.eval_every": _COUNT,
    "runtime.eval_views": _COUNT,
    "runtime.eval_metrics": _Bool(),
    "runtime.usd_every": _COUNT,
    "runtime.max_consecutive_failures": _POSITIVE,
    "runtime.progress": _Bool(),
    "runtime.image_scale": _float(0.0, 1.0, lo_open=True, optional=True),  # the loop only ever downscales
    "runtime.stop_at": _int(0, optional=True),
    # -- top level
    "kind": _enum(SceneKind, optional=True),
    "sh_degree": _int(0, _SH_MAX, optional=True),
    "background": _Colour(),
    "filter_sigma": _float(*FILTER_SIGMA_RANGE),
})

# the nested stage configs: FitConfig field name -> its dataclass
_GROUPS = MappingProxyType({f.name: f.default_factory for f in dataclasses.fields(FitConfig)
                            if f.default_factory is not dataclasses.MISSING})


def validate_config(cfg) -> None:
    """Check every field of a :class:`FitConfig` and the relations between fields.

    Runs the :data:`FIELD_CHECKS` table (one check per dotted leaf path), then the cross-field
    checks. Nothing is changed; string values of enum fields are accepted as they are.

    Args:
        cfg: the configuration.

    Raises:
        TypeError: ``cfg`` is not a FitConfig, a stage group is not its config class, or a field has
            a wrong type (a bool or float where an int is needed, a non-string where a string is).
        ValueError: a value is out of range, NaN or infinite, not one of the accepted choices, or
            two fields contradict each other (``optim.means_final > optim.means``).
    """
    if not isinstance(cfg, FitConfig):
        raise TypeError(f"config must be a wtopo.FitConfig, got {type(cfg).__name__}")
    for name, cls in _GROUPS.items():
        group = getattr(cfg, name)
        if not isinstance(group, cls):
            _fail(f"{_PREFIX}.{name}", f"a {cls.__name__}", group, type_error=True)
    for path, check in FIELD_CHECKS.items():
        obj = cfg
        for part in path.split("."):
            obj = getattr(obj, part)
        check(f"{_PREFIX}.{path}", obj)
    o = cfg.optim
    if o.means > 0 and o.means_final > 0 and o.means_final > o.means:
        raise ValueError(f"{_PREFIX}.optim.means_final must be <= {_PREFIX}.optim.means (the learning rate "
                         f"decays), got means_final={o.means_final!r} > means={o.means!r}")
