# SPDX-License-Identifier: Apache-2.0
"""Which vertices a view's rendered depth map supports, on CPU and CUDA through Warp (``kernels/vertex_support.py``).

The final mesh's support rules (:func:`wtopo.geometry.mesh_policy.supported_components` and
:func:`~wtopo.geometry.mesh_policy.supported_faces`) ask, view after view, which of the still undecided vertices
project onto a pixel whose depth agrees with theirs. This is one launch per view over those vertices, in float64
like the NumPy formulation it replaces (``tests/reference/vertex_support.py``), so the decisions are the same on
every device but for a vertex within a rounding of a pixel's edge or of the tolerance (a CUDA compiler may fuse
a multiply and an add). Nothing here is differentiated.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from . import _bridge
from ._validate import require_tensor, value_checks
from .camera import Camera
from .kernels import vertex_support as _k

__all__ = ["view_agreement"]

_CPU_STRIP = 64  # vertices per CPU thread
_MIN_CHUNK = 64  # CPU threads per launch at least, when split


def view_agreement(vertices: torch.Tensor, index: torch.Tensor, camera: Camera, depth: torch.Tensor, *,
                   tolerance: float | None = None, relative: float = 0.02) -> torch.Tensor:
    """Whether each listed vertex lands, in front of ``camera`` and inside its image, on a pixel of ``depth`` that
    is positive and agrees with the vertex's z-depth.

    Args:
        vertices: ``[V, 3]`` float64, the camera's frame of reference (world units).
        index: ``[A]`` int64, the vertices to test (any order, repeats allowed), each in ``[0, V)`` (checked, with a
            host synchronisation, except under :func:`wtopo._validate.trusted_values`).
        camera: the view (pinhole with skew, and OpenCV distortion when it has one).
        depth: ``[H, W]`` float32 or float64 z-depth map of the camera's size (0: no surface), on ``vertices``'
            device.
        tolerance: largest ``|depth - z|`` that agrees (world units, > 0); ``None``: ``relative`` times the vertex's
            z-depth.
        relative: see ``tolerance`` (> 0).

    Returns:
        ``[A]`` bool on ``vertices``' device. Not differentiable.

    Raises:
        TypeError: non-tensors or wrong dtypes.
        ValueError: wrong shapes, a depth map not of the camera's size, mismatched devices, a tolerance that is not
            a positive finite number.
    """
    require_tensor("vertices", vertices, ndim=2, shape=(None, 3), dtypes=(torch.float64,))
    require_tensor("index", index, ndim=1, dtypes=(torch.int64,))
    require_tensor("depth", depth, shape=(camera.height, camera.width))
    dev = vertices.device
    for name, t in (("index", index), ("depth", depth)):
        if t.device != dev:
            raise ValueError(f"{name} must be on {dev} like vertices, got {t.device}")
    tol = relative if tolerance is None else tolerance
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"{'relative' if tolerance is None else 'tolerance'} must be a finite number > 0, got {tol!r}")
    n = int(index.shape[0])
    agree = torch.empty(n, dtype=torch.uint8, device=dev)
    if n == 0:
        return agree.bool()
    if value_checks():  # host sync: validation only (the mesh policy's indices are its own)
        lo, hi = int(index.min()), int(index.max())
        if lo < 0 or hi >= vertices.shape[0]:
            raise ValueError(f"index must lie in [0, {vertices.shape[0]}), got values from {lo} to {hi}")
    K = camera.K
    lens = np.zeros(5) if camera.distortion is None else np.asarray(camera.distortion, np.float64)
    wdev = _bridge.warp_device(dev)
    strip = _CPU_STRIP if wdev.is_cpu else 1
    args = [strip, _bridge.to_warp(vertices.contiguous(), wp.vec3d), _bridge.to_warp(index.contiguous()),
            wp.mat33d(*np.asarray(camera.R, np.float64).reshape(-1)), wp.vec3d(*np.asarray(camera.t, np.float64)),
            _k.lens_vec(K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]), _k.lens_vec(*lens),
            int(camera.distortion is not None), _bridge.to_warp(depth.contiguous()),
            wp.float64(tol if tolerance is not None else -tol)]
    with _bridge.torch_stream(wdev, dev):
        _bridge.launch_split(_k.view_agreement_kernel, -(-n // strip), args, [_bridge.to_warp(agree)], device=wdev,
                             min_chunk=_MIN_CHUNK)
    return agree.bool()
