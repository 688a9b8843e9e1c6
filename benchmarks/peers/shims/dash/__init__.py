# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``dash``: Open3D's ``draw_plotly`` module imports ``Dash``, ``html`` and ``dcc`` at import
time for its web viewer only, which the peers benchmark never uses. Any use raises."""


class _Unavailable:
    def __init__(self, *a, **k):
        raise RuntimeError("dash: the peers benchmark's stand-in has no web viewer")

    def __getattr__(self, name):
        raise RuntimeError(f"dash.{name}: the peers benchmark's stand-in has no web viewer")


Dash = _Unavailable
html = dcc = _Unavailable.__new__(_Unavailable)
