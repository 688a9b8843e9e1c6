# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``igl`` (libigl's bindings): ``pgsr_dpsr``'s ``nvdiffrast_utils/dpsr_utils.py`` imports
``adjacency_matrix`` and ``connected_components`` for ``verts_on_largest_mesh``, which its training never
calls. Any use raises."""


def adjacency_matrix(*args, **kwargs):
    raise RuntimeError("igl.adjacency_matrix: the peers benchmark's stand-in has no libigl")


def connected_components(*args, **kwargs):
    raise RuntimeError("igl.connected_components: the peers benchmark's stand-in has no libigl")
