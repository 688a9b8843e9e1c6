# SPDX-License-Identifier: Apache-2.0
"""Warp kernels of wtopo, one module per operation (installed as ``wtopo.kernels``).

Only ``@wp.func``, ``@wp.kernel``, ``@wp.struct`` and lookup tables live here; validation,
allocation, launches and torch bridges are in the matching ``wtopo/<op>.py`` module.
"""
