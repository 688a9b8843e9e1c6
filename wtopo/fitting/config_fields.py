# SPDX-License-Identifier: Apache-2.0
"""The one walk over a :class:`~wtopo.fitting.config.FitConfig`'s leaf fields (:func:`leaves`) and the
setter built on it (:func:`set_field`), used by :meth:`~wtopo.fitting.config.FitConfig.from_dict`, the
CLI's ``--set`` and :func:`~wtopo.fitting.validate_config.validate_config`."""

from __future__ import annotations

import dataclasses
import enum
import functools
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass

__all__ = ["Leaf", "leaves", "set_field", "REMOVED", "RemovedFieldError", "removed_fields"]

_REJECTED, _FIXED = "measured and not kept", "now a fixed constant"
REMOVED: dict[str, tuple[str, object]] = {
    # rejected ideas: the fit always runs as with the former default (design/decisions.md says why)
    "optim.means_restart_along_normal": (_REJECTED, False),
    "losses.mesh_start_fraction": (_REJECTED, 0.0),
    "losses.mesh_end_fraction": (_REJECTED, 1.0),
    "losses.mesh_thin_probe": (_REJECTED, None),
    "losses.mesh_depth_robust": (_REJECTED, 0.0),
    "losses.mesh_depth_robust_behind": (_REJECTED, False),
    "losses.mesh_depth_behind": (_REJECTED, 1.0),
    "losses.mesh_photo_gate": (_REJECTED, 0.0),
    "losses.mesh_view_support": (_REJECTED, 0),
    "losses.mesh_inset": (_REJECTED, 0),
    "losses.mesh_depth_source": (_REJECTED, "median"),
    "losses.multiview_geometric": (_REJECTED, 0.0),
    "losses.silhouette_band": (_REJECTED, 0),
    "losses.mask_halo": (_REJECTED, False),
    "mesh.silhouette_gain": (_REJECTED, 0.0),
    "mesh.curvature_compensation": (_REJECTED, False),
    "mesh.support_voxels": (_REJECTED, 0.0),
    "mesh.opacity_threshold": (_REJECTED, 0.0),
    "densify.geometry_densify_voxels": (_REJECTED, 0.0),
    "final.method": (_REJECTED, "tsdf"),
    "final.closure": (_REJECTED, "poisson"),
    "final.silhouette_calibration": (_REJECTED, False),
    "final.largest_component": (_REJECTED, False),
    "tsdf.backend": (_REJECTED, "warp"),
    # internal constants nobody should tune: the value the fit now always uses
    "init.opacity": (_FIXED, 0.3),
    "optim.means_thin_decay": (_FIXED, 0.5),
    "optim.sh_rest": (_FIXED, 5e-4),
    "tsdf.truncation_voxels": (_FIXED, 4.0),
    "tsdf.depth": (_FIXED, "median"),
    "tsdf.alpha_threshold": (_FIXED, 0.5),
    "coevolution.correspondence_fraction": (_FIXED, 0.5),
    "final.poisson_resolution": (_FIXED, 128),
    "densify.start_fraction": (_FIXED, 0.25),
    "densify.stop_fraction": (_FIXED, 0.8),
    "densify.grad_threshold": (_FIXED, 5e-4),
    "densify.max_growth": (_FIXED, 0.5),
    "densify.percent_dense": (_FIXED, 0.01),
    "densify.prune_opacity": (_FIXED, 0.05),
    "densify.geometry_prune_distance": (_FIXED, 0.02),
    "densify.geometry_prune_opacity": (_FIXED, 0.3),
    "losses.normal_start_fraction": (_FIXED, 0.5),
    "losses.distortion_start_fraction": (_FIXED, 0.5),
    "losses.multiview_start_fraction": (_FIXED, 0.5),
    "losses.multiview_pixels": (_FIXED, 4096),
    "mesh.padding": (_FIXED, 0.1),
    "mesh.offset": (_FIXED, 0.5),
    "mesh.offset_weight": (_FIXED, 0.5),
    "mesh.sign_distance": (_FIXED, 3.0),
    "runtime.checkpoint_seconds": (_FIXED, 120.0),
    "runtime.keep_checkpoints": (_FIXED, 2),
    "runtime.max_consecutive_failures": (_FIXED, 20),
}
"""Fields earlier versions of :class:`FitConfig` had, by dotted path: ``(why it went, the value the fit now
always behaves as)``. Setting one raises :class:`RemovedFieldError`."""


def removed_fields(paths) -> str:
    """One line per removed field of ``paths``: why it went and the value the fit now behaves as."""
    return "; ".join(f"{p} ({REMOVED[p][0]}; the fit behaves as with {REMOVED[p][1]!r})" for p in paths)


class RemovedFieldError(ValueError):
    """A configuration sets fields this version of :class:`FitConfig` no longer has.

    Attributes:
        paths: the dotted paths of the removed fields.
    """

    def __init__(self, paths, *, saved: bool = False):
        self.paths = list(paths)
        where = " (a configuration saved by an older version?)" if saved else ""
        super().__init__(f"FitConfig field{'s' if len(self.paths) > 1 else ''} removed{where}: "
                         f"{removed_fields(self.paths)}. Delete {'them' if len(self.paths) > 1 else 'it'} from the "
                         "configuration; see design/decisions.md for why.")


@dataclass(frozen=True)
class Leaf:
    """One leaf field of a :class:`FitConfig`, as :func:`leaves` finds it."""

    path: str
    """Dotted path below ``FitConfig`` (``"warmup.iterations"``)."""
    owner: object
    """The (stage) config holding the field."""
    field: dataclasses.Field
    """The field; ``field.metadata`` holds its ``"check"`` (or ``"pattern"`` for a string)."""
    type: object
    """The resolved type annotation (``int | None``, an enum class, ...)."""

    @property
    def value(self):
        """The field's current value."""
        return getattr(self.owner, self.field.name)

    @property
    def base(self):
        """The annotation without ``None`` (``int`` for ``int | None``)."""
        return _base_type(self.type)

    def set(self, value) -> None:
        """Set the field from a Python or JSON value: an enum's string becomes its member (unknown strings
        raise ``ValueError`` naming the path and the members), a list becomes a tuple; nothing else is
        converted but a boolean for a field that was one in earlier versions (``was_bool``: 1 / 0)
        (:func:`~wtopo.fitting.validate_config.validate_config` checks the rest)."""
        base = self.base
        if isinstance(value, bool) and self.field.metadata.get("was_bool"):
            value = float(value)
        if isinstance(base, type) and issubclass(base, enum.Enum) and isinstance(value, str):
            try:
                value = base(value)
            except ValueError:
                raise ValueError(f"{self.path} must be one of {[m.value for m in base]}, got {value!r}") from None
        elif isinstance(value, list):  # the only sequences in FitConfig are tuples (background)
            value = tuple(value)
        setattr(self.owner, self.field.name, value)


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _base_type(hint):
    """``X`` for ``X | None``, else ``hint`` itself."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return args[0] if len(args) == 1 else hint
    return hint


def leaves(cfg, prefix: str = "") -> Iterator[Leaf]:
    """Every leaf field below ``cfg`` (a :class:`FitConfig` or a stage config), in declaration order.

    The one walk over the configuration: :meth:`FitConfig.from_dict`, :func:`set_field` (the CLI's
    ``--set``) and :func:`~wtopo.fitting.validate_config.validate_config` all use it.

    Raises:
        TypeError: a stage group is not its config class.
    """
    hints = _hints(type(cfg))
    for f in dataclasses.fields(cfg):
        hint, value, path = hints[f.name], getattr(cfg, f.name), prefix + f.name
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, hint):
                raise TypeError(f"FitConfig.{path} must be a {hint.__name__}, got {value!r} ({type(value).__name__})")
            yield from leaves(value, path + ".")
        else:
            yield Leaf(path, cfg, f, hint)


def set_field(cfg, path: str, value) -> None:
    """Set the leaf at dotted ``path`` (:meth:`Leaf.set`).

    Raises:
        RemovedFieldError: ``path`` is a field earlier versions had (:data:`REMOVED`).
        ValueError: an unknown path or a group.
    """
    if path in REMOVED:
        raise RemovedFieldError([path])
    for leaf in leaves(cfg):
        if leaf.path == path:
            leaf.set(value)
            return
    if any(leaf.path.startswith(path + ".") for leaf in leaves(cfg)):
        raise ValueError(f"{path!r} is a group of FitConfig, set one of its fields")
    raise ValueError(f"FitConfig has no field {path!r}")
