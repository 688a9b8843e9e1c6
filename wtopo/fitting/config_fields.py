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

__all__ = ["Leaf", "leaves", "set_field"]


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
    """Set the leaf at dotted ``path`` (:meth:`Leaf.set`); an unknown path or a group raises ``ValueError``."""
    for leaf in leaves(cfg):
        if leaf.path == path:
            leaf.set(value)
            return
    if any(leaf.path.startswith(path + ".") for leaf in leaves(cfg)):
        raise ValueError(f"{path!r} is a group of FitConfig, set one of its fields")
    raise ValueError(f"FitConfig has no field {path!r}")
