# SPDX-License-Identifier: Apache-2.0
"""Error measures for reconstructed meshes and rendered images.

Geometry (host, float64, SciPy ``cKDTree``): :func:`chamfer`, :func:`chamfer_vertices`,
:func:`f_score` (and its two halves with their components and areas: :func:`floaters`, reconstructed
surface far from the truth, and :func:`holes`, true surface far from the reconstruction),
:func:`normal_consistency`, :func:`mesh_stats`, and for scenes
:func:`roi_f_score` (Tanks-and-Temples F-score inside a region of interest) and
:func:`camera_clearance` (how close a mesh comes to the cameras); for recovered camera poses
:func:`align_similarity` (least-squares similarity between two point sets, Umeyama). Surfaces are
sampled uniformly by area; distances are exact point-to-triangle distances to the other surface (closest face from
Warp's BVH, distance recomputed in float64), so the result does not carry the sampling
density's bias of a plain point-to-point Chamfer.

Images (torch, differentiable): :func:`psnr`, :func:`ssim`.

Meshes may be given as a ``trimesh.Trimesh`` or a ``(verts [V, 3], faces [F, 3])`` pair of numpy
arrays or torch tensors.

Modules (private; import from ``wtopo.metrics``):

* ``_surface``: mesh input, area sampling (:func:`sample_surface`) and exact closest-point queries;
* ``_distance``: :func:`chamfer`, :func:`chamfer_vertices`, :func:`f_score`, :func:`normal_consistency`;
* ``_topology``: :func:`mesh_stats`, :func:`floaters`, :func:`holes`;
* ``_observed``: :func:`observed_chamfer` (Chamfer on the part of the truth the training views saw),
  :func:`view_counts`;
* ``_scene``: :func:`roi_f_score`, :func:`camera_clearance`;
* ``_alignment``: :func:`align_similarity`, :func:`refine_alignment`;
* ``_image``: :func:`psnr`, :func:`ssim`.
"""

from ._alignment import SimilarityAlignment, align_similarity, refine_alignment
from ._distance import (
    ChamferResult,
    FScore,
    InwardOffset,
    chamfer,
    chamfer_vertices,
    f_score,
    inward_offset,
    normal_consistency,
)
from ._image import psnr, ssim
from ._observed import ObservedChamfer, observed_chamfer, view_counts
from ._scene import ROIFScore, camera_clearance, roi_f_score
from ._surface import sample_surface
from ._topology import Floaters, Holes, floaters, holes, mesh_stats

__all__ = [
    "ChamferResult",
    "FScore",
    "InwardOffset",
    "inward_offset",
    "Floaters",
    "Holes",
    "chamfer",
    "chamfer_vertices",
    "f_score",
    "floaters",
    "holes",
    "normal_consistency",
    "ObservedChamfer",
    "observed_chamfer",
    "view_counts",
    "psnr",
    "ssim",
    "mesh_stats",
    "sample_surface",
    "ROIFScore",
    "roi_f_score",
    "camera_clearance",
    "SimilarityAlignment",
    "align_similarity",
    "refine_alignment",
]
