# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``pytorch3d.structures``: ``pgsr_dpsr``'s ``nvdiffrast_utils/dpsr_utils.py`` imports ``Meshes``
for ``mesh_rasterization``, which its training never calls. Any use raises."""


class Meshes:
    def __init__(self, *args, **kwargs):
        raise RuntimeError("pytorch3d.structures.Meshes: the peers benchmark's stand-in has no mesh structure")
