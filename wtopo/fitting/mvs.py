# SPDX-License-Identifier: Apache-2.0
"""The stereo helpers of :mod:`wtopo.geometry.mvs` under the names ``plan``, ``geometric`` and
``view_support`` import them by.

Those three modules are being rewritten on the configuration branch; once it has landed they import
:mod:`wtopo.geometry.mvs` directly and this module goes.
"""

from ..geometry.mvs import TorchCam as _TorchCam
from ..geometry.mvs import TorchCams as _TorchCams
from ..geometry.mvs import gray as _gray
from ..geometry.mvs import select_neighbours

__all__ = ["_TorchCam", "_TorchCams", "_gray", "select_neighbours"]
