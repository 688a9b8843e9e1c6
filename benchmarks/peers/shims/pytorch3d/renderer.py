# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``pytorch3d.renderer``: ``pgsr_dpsr``'s ``nvdiffrast_utils/dpsr_utils.py`` imports
``PerspectiveCameras`` and ``rasterize_meshes`` for ``mesh_rasterization``, which its training never calls
(its mesh renderer is nvdiffrast's). Any use raises."""


class PerspectiveCameras:
    def __init__(self, *args, **kwargs):
        raise RuntimeError("pytorch3d.renderer.PerspectiveCameras: the peers benchmark's stand-in has no renderer")


def rasterize_meshes(*args, **kwargs):
    raise RuntimeError("pytorch3d.renderer.rasterize_meshes: the peers benchmark's stand-in has no renderer")
