# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``addict``: Open3D imports its ``open3d.ml`` configuration helpers at import time; the peers
benchmark never uses them. ``Dict`` is a plain dict with attribute access."""


class Dict(dict):
    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None
