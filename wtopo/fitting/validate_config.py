# SPDX-License-Identifier: Apache-2.0
"""Validation of a :class:`~wtopo.fitting.config.FitConfig` before :func:`wtopo.fit` does any work.

Each field's check is derived from its type annotation plus the ``"check"`` in its
``dataclasses.field`` metadata (a :class:`~wtopo.fitting.config.Range`, or a tuple of accepted
ints); :func:`validate_config` walks the fields with :func:`~wtopo.fitting.config.leaves`, then runs
the cross-field checks. A wrong type raises :class:`TypeError`, a value out of range
:class:`ValueError`; both name the field by its dotted path and give the bad value, e.g.
``FitConfig.warmup.iterations must be an int >= 0 or None, got -3``.

Type rules: ``bool`` is not an int (nor a number); an ``int`` is accepted where a float is; numbers
must be Python ``int`` / ``float`` (the configuration is JSON-serialised into checkpoints, which a
NumPy ``float32`` or ``int64`` breaks); an enum field takes the member or its string value.
"""

from __future__ import annotations

import enum
import math
import re
import typing

from .config import FitConfig, Leaf, Range, leaves

__all__ = ["validate_config", "check_leaf"]

_PREFIX = "FitConfig"


def _fail(path: str, expect: str, value, *, type_error: bool = False):
    if type_error:
        raise TypeError(f"{path} must be {expect}, got {value!r} ({type(value).__name__})")
    raise ValueError(f"{path} must be {expect}, got {value!r}")


def _check_number(path: str, v, integer: bool, rng: Range, none: str) -> None:
    expect = f"{'an int' if integer else 'a finite number'} {rng}{none}"
    if isinstance(v, bool) or not isinstance(v, int if integer else (int, float)):
        _fail(path, expect, v, type_error=True)
    if (isinstance(v, float) and not math.isfinite(v)) or v not in rng:
        _fail(path, expect, v)


def check_leaf(leaf: Leaf, prefix: str = _PREFIX) -> None:
    """Check one field's value against its annotation and metadata (see the module docstring).

    Raises:
        TypeError: the value has a wrong type.
        ValueError: the value is out of range or not one of the accepted choices.
    """
    path, v, base = f"{prefix}.{leaf.path}", leaf.value, leaf.base
    optional = base is not leaf.type
    if v is None and optional:
        return
    none = " or None" if optional else ""
    check = leaf.field.metadata.get("check")
    if base is bool:
        if not isinstance(v, bool):
            _fail(path, f"a bool{none}", v, type_error=True)
    elif isinstance(check, tuple):  # an int out of a few accepted values
        expect = "an int, one of " + ", ".join(str(c) for c in check)
        if isinstance(v, bool) or not isinstance(v, int):
            _fail(path, expect, v, type_error=True)
        if v not in check:
            _fail(path, expect, v)
    elif base in (int, float):
        _check_number(path, v, base is int, check, none)
    elif isinstance(base, type) and issubclass(base, enum.Enum):
        expect = (f"one of {', '.join(repr(m.value) for m in base)} (or a {base.__name__}){none}")
        if isinstance(v, base):
            return
        if not isinstance(v, str):
            _fail(path, expect, v, type_error=True)
        if v not in {m.value for m in base}:
            _fail(path, expect, v)
    elif base is str:
        pattern = leaf.field.metadata["pattern"]
        expect = f"a string matching {pattern!r}"
        if not isinstance(v, str):
            _fail(path, expect, v, type_error=True)
        if not re.fullmatch(pattern, v):
            _fail(path, expect, v)
    elif _tuple_len(base):  # a fixed-length tuple of numbers in the check's range (a colour)
        n = _tuple_len(base)
        expect = f"a tuple of {n} numbers {check}{none}"
        if not isinstance(v, (tuple, list)):
            _fail(path, expect, v, type_error=True)
        if len(v) != n:
            _fail(path, expect, v)
        for i, c in enumerate(v):
            _check_number(f"{path}[{i}]", c, False, check, "")
    else:
        raise TypeError(f"{path}: no check for a field of type {leaf.type!r}")  # a FitConfig bug, not user input


def _tuple_len(hint) -> int:
    """``n`` for ``tuple[X, ..., X]`` of ``n`` items, else 0."""
    return len(typing.get_args(hint)) if typing.get_origin(hint) is tuple else 0


def validate_config(cfg) -> None:
    """Check every field of a :class:`FitConfig` and the relations between fields.

    Walks the fields with :func:`~wtopo.fitting.config.leaves` and runs :func:`check_leaf` on each,
    then the cross-field checks. Nothing is changed; string values of enum fields are accepted as
    they are.

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
    for leaf in leaves(cfg):
        check_leaf(leaf)
    o = cfg.optim
    if o.means > 0 and o.means_final > 0 and o.means_final > o.means:
        raise ValueError(f"{_PREFIX}.optim.means_final must be <= {_PREFIX}.optim.means (the learning rate "
                         f"decays), got means_final={o.means_final!r} > means={o.means!r}")
