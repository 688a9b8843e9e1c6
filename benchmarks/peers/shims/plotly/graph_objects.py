# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``plotly.graph_objects`` (see the package docstring)."""


def __getattr__(name):
    raise RuntimeError(f"plotly.graph_objects.{name}: the peers benchmark's stand-in has no plotting")
