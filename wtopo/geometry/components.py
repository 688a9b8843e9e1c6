# SPDX-License-Identifier: Apache-2.0
"""Connected components of a triangle mesh's faces, shared by the mesh metrics and the TSDF fusion."""

from __future__ import annotations

import numpy as np

__all__ = ["face_components"]


def face_components(f: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Connected components of faces [F, 3] (int) that share a vertex: ``(count, label [F] int64)``.

    SciPy's connected components of the vertex graph of the face edges, each face then labelled by its first
    vertex: 0.75 s for 2.6M faces on 2 CPU cores, where labelling trimesh's edge-sharing ``face_adjacency``
    takes 9 s. Two sheets that touch at a single vertex are one component here (two through shared edges).
    Used by the mesh statistics of :mod:`wtopo.metrics`, the TSDF fusion's closing step
    (:mod:`wtopo.tsdf_fusion`), the meshing policy (:mod:`.mesh_policy`) and the fit's report."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(f, np.int64).reshape(-1, 3)
    if len(f) == 0:
        return 0, np.zeros(0, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices)).tocsr()
    _, vlabel = connected_components(graph, directed=False)
    # compact: vertices no face uses are components of their own. Numbered in the order of SciPy's labels, as
    # np.unique(..., return_inverse=True) numbers them, by a table instead of a sort (0.03 s against 0.3 s at 2.6M)
    first = vlabel[f[:, 0]]
    present = np.zeros(n_vertices, bool)
    present[first] = True
    number = np.cumsum(present, dtype=np.int64) - 1
    return int(number[-1]) + 1, number[first]
