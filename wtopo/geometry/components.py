# SPDX-License-Identifier: Apache-2.0
"""Connected components of a triangle mesh's faces, shared by the mesh metrics and the TSDF fusion."""

from __future__ import annotations

import numpy as np

__all__ = ["face_components"]


def face_components(f: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Connected components of faces [F, 3] (int) that share a vertex: ``(count, label [F] int64)``.

    SciPy; used by the mesh statistics of :mod:`wtopo.metrics` and the TSDF fusion's closing step
    (:mod:`wtopo.tsdf_fusion`)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = len(f)
    if nf == 0:
        return 0, np.zeros(0, np.int64)
    rows = np.repeat(np.arange(nf), 3)
    adj = coo_matrix((np.ones(3 * nf), (rows, f.reshape(-1))), shape=(nf, n_vertices)).tocsr()
    n, label = connected_components(adj @ adj.T, directed=False)
    return int(n), label.astype(np.int64)
