# SPDX-License-Identifier: Apache-2.0
"""Value kinds of the fit's configuration: the accepted range of a numeric field (:class:`Range`,
kept in the field's metadata and checked by :mod:`wtopo.fitting.validate_config`) and the
enumerations its fields take. :mod:`wtopo.fitting.config` re-exports every name here."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

__all__ = ["Range", "RATE", "FRACTION", "COUNT", "POSITIVE", "NormalFlip", "DepthLoss", "InitSource",
           "PoissonBox", "Preset"]


@dataclass(frozen=True)
class Range:
    """The accepted interval of a numeric field, kept in its ``dataclasses.field`` metadata (``"check"``).

    Whether the field takes an int or a float, and ``None``, comes from its type annotation.
    """

    lo: float
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def __str__(self) -> str:
        lo, hi = (f"{x:g}" if isinstance(x, float) else x for x in (self.lo, self.hi))
        if hi is None:
            return f"{'>' if self.lo_open else '>='} {lo}"
        return f"in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"

    def __contains__(self, v) -> bool:
        below = v <= self.lo if self.lo_open else v < self.lo
        above = self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi)
        return not (below or above)


RATE = Range(0.0)  # a learning rate or loss weight: finite and >= 0
FRACTION = Range(0.0, 1.0)  # a fraction, opacity threshold or weight in [0, 1]
COUNT = Range(0)  # iterations, intervals where 0 disables, counts
POSITIVE = Range(1)  # intervals and counts that must be at least 1


def _f(default, check, *, was_bool: bool = False):
    """A field with ``default`` and its check: a :class:`Range`, or a tuple of the accepted ints.
    ``was_bool``: the field was a boolean in earlier versions; a saved or typed ``true`` / ``false``
    reads as 1 / 0 (:meth:`~wtopo.fitting.config_fields.Leaf.set`)."""
    return field(default=default, metadata={"check": check, "was_bool": was_bool})


class Preset(str, enum.Enum):
    """A point on the error-against-time front (``FitConfig.preset``, ``--preset``):
    the budgets the plan starts from (:mod:`wtopo.fitting.presets`)."""

    FAST = "fast"
    """A first look in about a third of the time: fewer iterations, smaller images and grids."""
    BALANCED = "balanced"
    """The default: the front's knee, close to ``BEST``'s error in a fraction of its time."""
    BEST = "best"
    """Lowest error on the front: more iterations where they still pay."""


class NormalFlip(str, enum.Enum):
    """How the sign of each surfel normal fed to the Poisson solve is chosen."""

    MESH = "mesh"
    """Mesh normal where the nearest proxy face is close and agrees, view directions otherwise."""
    VIEW = "view"
    """Only the accumulated directions towards the cameras that saw the surfel."""
    RANDOM = "random"
    """A random sign per surfel (ablation: shows what the alignment buys)."""


class DepthLoss(str, enum.Enum):
    """Form of the mesh-depth agreement term."""

    LOG_RATIO = "log_ratio"
    """``|log D_surfel - log D_mesh|`` (the method description)."""
    LOG1P_ABS = "log1p_abs"
    """``log1p(|D_mesh - D_surfel| / extent)`` (the public TopoSurfel code)."""


class InitSource(str, enum.Enum):
    """Where the initial surfels come from."""

    AUTO = "auto"
    """The scene's points when it has them (at least 100); else ``MVS`` for a scene without masks,
    ``CAMERAS`` for a masked object."""
    POINTS = "points"
    """The scene's points (an error without them)."""
    MVS = "mvs"
    """Plane-sweep stereo over the training views (:mod:`wtopo.geometry.mvs`): confirmed depths
    as oriented points."""
    CAMERAS = "cameras"
    """Random points in the cameras' common volume."""


class PoissonBox(str, enum.Enum):
    """The domain of the proxy's Poisson solve."""

    UNIT = "unit"
    """The normalised unit cube."""
    INITIAL_MESH = "initial_mesh"
    """The TSDF mesh's box + 10 % (public TopoSurfel code)."""


_GRID_MIN = 8  # coarser Poisson / TSDF grids cannot resolve any shape
_POISSON_MAX = 1024  # the Poisson grid is dense (FFT): 1024^3 complex nodes already take 8 GiB per buffer
