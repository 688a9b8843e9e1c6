# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``mediapy`` on machines without IPython: 2DGS's ``render.py`` imports it for its videos only,
which the peers benchmark never writes. Any use raises."""


def __getattr__(name):
    raise RuntimeError(f"mediapy.{name}: the peers benchmark's stand-in has no video support")
