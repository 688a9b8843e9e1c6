# SPDX-License-Identifier: Apache-2.0
"""Atomic, validated, resumable checkpoints (design/stability.md, "Not losing work").

A checkpoint holds the surfel parameters and buffers, the optimiser state, the loop state (stage,
iteration, accumulators, history), RNG states (torch, NumPy, Python), the scene normalisation, a
config hash and the package versions. It is written with :func:`wtopo.io._common.atomic_write`
(temporary file in the same directory, fsync, :func:`os.replace`, directory fsync); the last
``keep`` checkpoints stay on disk. Loading validates shapes, finiteness and the config hash
and falls back to the previous checkpoint when the newest is unusable.
"""

from __future__ import annotations

import os
import random
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from ..io._common import atomic_write

__all__ = ["save_checkpoint", "load_checkpoint", "list_checkpoints", "rng_state", "set_rng_state", "versions",
           "CheckpointError"]

_NAME = re.compile(r"^ckpt_(\d{8})\.pt$")


class CheckpointError(RuntimeError):
    """No usable checkpoint (all missing, corrupt, non-finite or from another configuration)."""


def versions() -> dict[str, str]:
    """Versions of wtopo, Warp and torch (stored in every checkpoint)."""
    import warp as wp

    from .. import __version__
    return {"wtopo": __version__, "warp": wp.config.version, "torch": torch.__version__}


def rng_state() -> dict:
    """The RNG states of torch (CPU and CUDA), NumPy and Python's ``random``."""
    st = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        st["cuda"] = torch.cuda.get_rng_state_all()
    return st


def set_rng_state(st: dict) -> None:
    """Restore states saved by :func:`rng_state`."""
    torch.set_rng_state(st["torch"])
    np.random.set_state(st["numpy"])
    random.setstate(st["python"])
    if "cuda" in st and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def list_checkpoints(directory: str | os.PathLike) -> list[Path]:
    """Checkpoints in ``directory``, oldest first."""
    d = Path(directory)
    if not d.is_dir():
        return []
    return sorted((p for p in d.iterdir() if _NAME.match(p.name)), key=lambda p: int(_NAME.match(p.name).group(1)))


def _finite(obj) -> bool:
    if isinstance(obj, torch.Tensor):
        return not obj.is_floating_point() or bool(torch.isfinite(obj).all())
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(_finite(v) for v in obj)
    return True


def save_checkpoint(directory: str | os.PathLike, step: int, state: dict, *, keep: int = 2) -> Path:
    """Write ``state`` atomically as ``directory/ckpt_<step>.pt`` and keep the newest ``keep``.

    ``state`` must hold ``"surfels"`` (a :meth:`Surfels.state_dict`) and ``"config_hash"``.
    Non-finite surfel state is refused (``ValueError``) so it never replaces a good checkpoint.
    """
    if keep < 2:
        raise ValueError(f"keep must be >= 2 (the fallback needs a previous checkpoint), got {keep}")
    if not _finite(state.get("surfels")):
        raise ValueError("refusing to checkpoint non-finite surfel parameters")
    d = Path(directory)
    final = d / f"ckpt_{step:08d}.pt"
    payload = dict(state, step=int(step), versions=versions())
    atomic_write(final, lambda tmp: torch.save(payload, tmp))
    for old in list_checkpoints(d)[:-keep]:
        old.unlink(missing_ok=True)
    return final


def _validate(payload: dict, config_hash: str | None) -> str | None:
    """Reason the payload is unusable, or ``None``."""
    for key in ("surfels", "step", "config_hash"):
        if key not in payload:
            return f"missing {key!r}"
    if config_hash is not None and payload["config_hash"] != config_hash:
        return f"config hash {payload['config_hash']} differs from this run's {config_hash}"
    params = payload["surfels"].get("params", {})
    n = {v.shape[0] for v in params.values()} | {v.shape[0] for v in payload["surfels"].get("buffers", {}).values()}
    if len(n) != 1:
        return f"surfel tensors disagree on the count: {sorted(n)}"
    if not _finite(payload["surfels"]):
        return "non-finite surfel parameters"
    return None


def load_checkpoint(directory: str | os.PathLike, *, config_hash: str | None = None) -> dict:
    """Newest valid checkpoint in ``directory``; invalid ones are skipped with a warning.

    Raises:
        CheckpointError: none is usable.
    """
    reasons = []
    for path in reversed(list_checkpoints(directory)):
        try:
            payload = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # noqa: BLE001 - any unreadable file means: fall back to the previous one
            reasons.append(f"{path.name}: unreadable ({type(exc).__name__}: {exc})")
            continue
        why = _validate(payload, config_hash)
        if why is None:
            for r in reasons:
                warnings.warn(f"skipped checkpoint {r}", RuntimeWarning, stacklevel=2)
            payload["path"] = str(path)
            return payload
        reasons.append(f"{path.name}: {why}")
    raise CheckpointError(f"no usable checkpoint in {directory}" + (": " + "; ".join(reasons) if reasons else ""))
