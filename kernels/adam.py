# SPDX-License-Identifier: Apache-2.0
"""Warp kernel of the fit's Adam step: one launch per parameter, every element once.

:func:`adam_step_kernel`, thread ``offset + tid`` = element ``i`` of a flattened parameter: a non-finite gradient
element is zeroed (``nan_to_num`` to 0) and raises ``flags[0]``; the moments and the parameter are updated as
``torch.optim.Adam`` updates them (no weight decay, no AMSGrad) in the order of its operations::

    m = m + (1 - b1) (g - m)               # lerp
    v = b2 v + ((1 - b2) g) g              # mul, addcmul
    p = p - step_size m / (sqrt(v) / root_correction + eps)

with ``step_size = lr / (1 - b1^t)`` and ``root_correction = sqrt(1 - b2^t)``; an updated element, or either of its
moments, that is not finite raises ``flags[0]`` too (a huge finite gradient whose square overflows the second
moment). A thread takes a strip of elements (1 on CUDA; on the CPU a thread's set-up costs
more than an element). Threads write disjoint elements (``flags`` only ever receives 1), so a CPU launch may be
split across threads.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def adam_step_kernel(offset: int, strip: int, param: wp.array(dtype=Any), grad: wp.array(dtype=Any),
                     exp_avg: wp.array(dtype=Any), exp_avg_sq: wp.array(dtype=Any), one_minus_b1: Any, b2: Any,
                     one_minus_b2: Any, step_size: Any, root_correction: Any, eps: Any,
                     flags: wp.array(dtype=wp.int32)):
    """Thread ``offset + tid``: elements ``strip * (offset + tid)`` onwards, ``strip`` of them (every array one
    parameter's, flattened, of one float dtype)."""
    i0 = (offset + wp.tid()) * strip
    for i in range(i0, wp.min(i0 + strip, param.shape[0])):
        g = grad[i]
        if not wp.isfinite(g):
            g = type(g)(0.0)
            grad[i] = g
            flags[0] = 1
        m = exp_avg[i]
        m = m + one_minus_b1 * (g - m)
        v = exp_avg_sq[i] * b2 + (one_minus_b2 * g) * g  # addcmul's order: g * g alone overflows sooner
        p = param[i] - step_size * (m / (wp.sqrt(v) / root_correction + eps))
        exp_avg[i] = m
        exp_avg_sq[i] = v
        param[i] = p
        if not (wp.isfinite(p) and wp.isfinite(v) and wp.isfinite(m)):
            flags[0] = 1
