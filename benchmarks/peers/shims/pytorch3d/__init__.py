# SPDX-License-Identifier: Apache-2.0
"""Stand-in for ``pytorch3d`` (no wheel for torch 2.11 / CUDA 13; the peers benchmark's own code, pure torch).

It provides exactly what the ``pgsr_dpsr`` peer imports: ``transforms.quaternion_to_matrix`` and
``transforms.matrix_to_quaternion`` (``scene/gaussian_model.py``), ``ops.knn_points``
(``utils/mesh_guided_densify_utils.py``), with pytorch3d's conventions; and ``structures.Meshes``,
``renderer.PerspectiveCameras`` / ``renderer.rasterize_meshes``, which ``nvdiffrast_utils/dpsr_utils.py``
imports at import time for functions its training never calls (any use raises).
"""
