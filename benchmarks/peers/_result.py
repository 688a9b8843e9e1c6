# SPDX-License-Identifier: Apache-2.0
"""A system's result folder: ``mesh.ply`` (normalised frame), ``renders.npz`` (held-out views), ``run.json``."""

from __future__ import annotations

import json
import os
import time

import numpy as np

__all__ = ["Clock", "read_json", "write_result"]


def read_json(path: str):
    """The JSON document at ``path``."""
    with open(path) as f:
        return json.load(f)


class Clock:
    """Wall time from images to mesh [s] and the peak GPU memory [bytes] of this process's torch allocator."""

    def __init__(self):
        import torch
        self.t0 = time.perf_counter()
        if torch.cuda.is_available():
            torch.cuda.reset_peak_memory_stats()

    def stop(self) -> dict:
        import torch
        out = {"wall_s": time.perf_counter() - self.t0}
        if torch.cuda.is_available():
            torch.cuda.synchronize()
            out["peak_gpu_bytes"] = int(torch.cuda.max_memory_allocated())
        return out


def write_result(out: str, *, system: str, mesh, renders: np.ndarray, run: dict) -> None:
    """Write one system's result. ``mesh``: trimesh (normalised frame); ``renders``: [T, H, W, 3] in [0, 1]."""
    os.makedirs(out, exist_ok=True)
    mesh.export(os.path.join(out, "mesh.ply"))
    np.savez_compressed(os.path.join(out, "renders.npz"), rgb=np.clip(renders, 0, 1).astype(np.float16))
    with open(os.path.join(out, "run.json"), "w") as f:
        json.dump({"system": system, **run}, f, indent=1)
