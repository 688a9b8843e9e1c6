# SPDX-License-Identifier: Apache-2.0
"""Outputs users open in their own tools: a USD timeline of the co-evolution, surfels as
3DGS-compatible PLY, meshes as PLY / OBJ.

* :class:`TimelineWriter` / :func:`read_timeline` / :func:`read_cameras` (:mod:`wtopo.io.usd`);
* :func:`write_surfels_ply` / :func:`read_surfels_ply` / :class:`SurfelArrays` and
  :func:`export_mesh` (:mod:`wtopo.io.ply`);
* :func:`export`, behind ``wtopo export`` (:mod:`wtopo.io.export`).
"""

from __future__ import annotations

from .export import EXPORT_FORMATS, export
from .ply import FLAT_LOG_SCALE, OPACITY_EPS, SurfelArrays, export_mesh, read_surfels_ply, write_surfels_ply
from .usd import (
    HAS_SPLAT_SCHEMA,
    SurfelEvent,
    Timeline,
    TimelineSample,
    TimelineStats,
    TimelineVerificationError,
    TimelineWriter,
    mesh_at,
    read_cameras,
    read_surfels,
    read_timeline,
)

__all__ = [
    "SurfelArrays", "write_surfels_ply", "read_surfels_ply", "export_mesh", "OPACITY_EPS", "FLAT_LOG_SCALE",
    "TimelineWriter", "TimelineStats", "TimelineVerificationError", "SurfelEvent", "Timeline", "TimelineSample",
    "read_timeline", "read_cameras", "read_surfels", "mesh_at", "HAS_SPLAT_SCHEMA", "export", "EXPORT_FORMATS",
]
