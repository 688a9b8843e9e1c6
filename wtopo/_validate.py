# SPDX-License-Identifier: Apache-2.0
"""Argument checks run at the Python boundary, before any kernel launch.

Every failure raises :class:`TypeError` or :class:`ValueError` whose message names the argument,
what was expected and what was given.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["require_tensor", "require_finite", "all_finite", "require_same_device", "require_positive",
           "require_int_range", "trusted_values", "value_checks"]

_trusted = contextvars.ContextVar("wtopo_trusted_values", default=False)


@contextlib.contextmanager
def trusted_values():
    """Skip the value checks that read the device (finiteness, ranges, index bounds) inside the block.

    For a caller whose tensors come from its own checked state, which vouches that they are finite
    and in range: the fit's iterations (its guards check losses, gradients and parameters after
    every step; its proxy-mesh faces come from marching cubes). Type, dtype, shape and device
    checks still run (they read no tensor data). Never around user data: an unchecked NaN can send
    a kernel out of bounds.
    """
    token = _trusted.set(True)
    try:
        yield
    finally:
        _trusted.reset(token)


def value_checks() -> bool:
    """Whether value checks run here (``False`` inside :func:`trusted_values`)."""
    return not _trusted.get()


def require_tensor(name: str, t, *, shape: Sequence[int | None] | None = None, dtypes=(torch.float32, torch.float64),
                   ndim: int | None = None) -> torch.Tensor:
    """Check that ``t`` is a tensor of an accepted dtype and a shape matching ``shape`` (``None`` = any size)."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if dtypes is not None and t.dtype not in dtypes:
        raise TypeError(f"{name} must have dtype in {[str(d) for d in dtypes]}, got {t.dtype}")
    if ndim is not None and t.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {tuple(t.shape)}")
    if shape is not None and (t.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, t.shape))):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    return t


def all_finite(t: torch.Tensor) -> bool:
    """Whether ``t`` holds no NaN or inf, by one reduction.  Host sync.

    A sum is non-finite when any term is (NaN and inf propagate); an overflow of huge finite values
    only makes it answer ``False`` for a finite tensor, so callers confirm a ``False`` with an exact
    search (:func:`require_finite` does).  On CPU NumPy's single-threaded SIMD sum is used: torch's
    ``isfinite`` / ``sum`` go through its intra-op thread pool, which stalls for tens of ms when the
    cores are oversubscribed (measured 60-80 ms per render on a loaded 2-core machine).
    """
    t = t.detach()
    if t.numel() == 0 or not (t.is_floating_point() or t.is_complex()):
        return True  # integers and booleans are always finite
    if t.is_complex():
        return bool(torch.isfinite(t).all())  # host sync
    if t.device.type == "cpu" and t.dtype in (torch.float16, torch.float32, torch.float64):
        with np.errstate(over="ignore", invalid="ignore"):
            total = t.numpy().sum()
    else:
        total = t.sum().item()  # host sync: validation only, never in a differentiable inner loop
    return math.isfinite(float(total))


def require_finite(name: str, t: torch.Tensor) -> torch.Tensor:
    """Raise if ``t`` holds NaN or inf, naming the first bad index and value.  Host sync.

    One reduction (:func:`all_finite`) when ``t`` is finite; the indexed search only when it is not,
    so the op wrappers call this directly on every launch.
    """
    if not value_checks() or all_finite(t):
        return t
    bad = ~torch.isfinite(t.detach())
    if bool(bad.any()):
        idx = tuple(int(i) for i in torch.nonzero(bad)[0].tolist())
        raise ValueError(f"{name} must be finite, got {t[idx].item()} at index {list(idx)}")
    return t


def require_same_device(**tensors) -> torch.device:
    """Check all given tensors live on one device and return it."""
    devs = {k: v.device for k, v in tensors.items() if isinstance(v, torch.Tensor)}
    uniq = set(devs.values())
    if len(uniq) > 1:
        desc = ", ".join(f"{k} on {v}" for k, v in devs.items())
        raise ValueError(f"all tensors must be on one device, got {desc}")
    return next(iter(uniq)) if uniq else torch.device("cpu")


def require_positive(name: str, value, *, allow_zero: bool = False) -> float:
    """Check a scalar is finite and > 0 (or >= 0)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not (v == v and abs(v) != float("inf")) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return v


def require_int_range(name: str, value, lo: int, hi: int | None = None) -> int:
    """Check an integer lies in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {value!r}")
    if value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name} must be {rng}, got {value}")
    return value
