# SPDX-License-Identifier: Apache-2.0
"""Warp kernel of the final mesh's support rules: does a rendered depth map put a surface where a vertex is?

:func:`view_agreement_kernel`, one thread per listed vertex (``index[i]``; a strip of ``strip`` of them on the CPU):
the vertex in the camera's frame (``R x + t``, float64), projected with the pinhole and, when ``distorted``, the
OpenCV lens (``multiview_ncc``'s projection), floored to the pixel it falls in; it agrees when it lies in front of
the camera, inside the image, on a pixel whose depth is positive and within ``tolerance`` of the vertex's z-depth
(``tolerance`` in the scene's units; negative: ``-tolerance`` times the vertex's z-depth). Writes 1 or 0 per listed
vertex. Nothing here is differentiated.
"""

from typing import Any

import warp as wp

from .multiview_ncc import _project_value

wp.set_module_options({"enable_backward": False})

lens_vec = wp.types.vector(length=5, dtype=wp.float64)
"""(fx, skew, cx, fy, cy), or (k1, k2, p1, p2, k3)."""


@wp.kernel
def view_agreement_kernel(offset: int, strip: int, vertices: wp.array(dtype=wp.vec3d),
                          index: wp.array(dtype=wp.int64), R: wp.mat33d, t: wp.vec3d, k: lens_vec, lens: lens_vec,
                          distorted: int, depth: wp.array2d(dtype=Any), tolerance: wp.float64,
                          agree: wp.array(dtype=wp.uint8)):
    """Thread ``offset + tid``: listed vertices ``strip * (offset + tid)`` onwards (``agree`` [len(index)])."""
    i0 = (offset + wp.tid()) * strip
    h = depth.shape[0]
    w = depth.shape[1]
    zero = wp.float64(0.0)
    for i in range(i0, wp.min(i0 + strip, index.shape[0])):
        p = R * vertices[int(index[i])] + t
        u, v = _project_value(p, k, lens, distorted)
        ok = wp.uint8(0)
        # NaN fails every comparison; the range test keeps the float -> int conversion in range
        if p[2] > zero and u >= zero and v >= zero and u < wp.float64(float(w)) and v < wp.float64(float(h)):
            d = wp.float64(depth[int(v), int(u)])  # u, v >= 0: truncation is the floor
            tol = tolerance
            if tol < zero:
                tol = -tol * p[2]
            if d > zero and wp.abs(d - p[2]) <= tol:
                ok = wp.uint8(1)
        agree[i] = ok
