# SPDX-License-Identifier: Apache-2.0
"""Chunked fitting of scenes larger than one device.

The region of interest is cut into overlapping chunks (:func:`plan_chunks`), each chunk is a normal
:func:`wtopo.fit` of the cameras that see it, run on ``torch.distributed`` (``torchrun``: one
process per GPU) or one after another in one process (:func:`fit_chunked`), and the chunks' cores
are merged: by default their surfels (:func:`merge_surfels`) are meshed once over the whole region of
interest by the fit's own final meshing (:func:`refuse_mesh`: one TSDF, no seam), or, with
``ChunkConfig(merge="weld")``, their meshes are cut to the cores and welded (:func:`merge_meshes`).

Command line::

    wtopo fit SCENE --out runs/x --chunks 4                                   # one process
    torchrun --nproc-per-node 2 -m wtopo.chunks.run SCENE --out runs/x --chunks 4 --device cuda
"""

from __future__ import annotations

from .engine import ChunkedResult, chunk_scene, dist_info, fit_chunked, rank_chunks
from .merge import merge_meshes, merge_surfels, refuse_mesh, refuse_resolution, weld_boundaries
from .partition import Chunk, ChunkConfig, ChunkPlan, assign_cameras, chunk_grid, core_owner, plan_chunks
from .synthetic import street_scene

__all__ = ["fit_chunked", "ChunkedResult", "ChunkConfig", "ChunkPlan", "Chunk", "plan_chunks", "chunk_grid",
           "assign_cameras", "core_owner", "chunk_scene", "rank_chunks", "dist_info", "merge_meshes",
           "merge_surfels", "weld_boundaries", "refuse_mesh", "refuse_resolution", "street_scene"]
