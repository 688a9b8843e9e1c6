# SPDX-License-Identifier: Apache-2.0
"""``pytorch3d.ops.knn_points``: exact K nearest neighbours of batched point clouds, pytorch3d's contract.

``knn_points(p1, p2, lengths1=None, lengths2=None, norm=2, K=1, version=-1, return_nn=False,
return_sorted=True)`` returns ``(dists, idx, knn)``: squared Euclidean distances (``norm=2``) or L1
distances (``norm=1``) [N, P1, K], indices into ``p2`` [N, P1, K] (int64), and the neighbours
[N, P1, K, D] when ``return_nn`` (else ``None``); always sorted nearest first. Entries past
``lengths1`` / ``lengths2`` (or past the K available neighbours) are zero, as in pytorch3d. ``dists`` is
recomputed from the chosen pairs with torch ops, so it carries gradients to ``p1`` and ``p2``.

The search is brute force in torch (chunked) for small problems and ``scipy.spatial.cKDTree`` (all
CPU cores) for large ones; both are exact, but which of two equidistant neighbours is returned may
differ from pytorch3d's CUDA kernel.
"""

from __future__ import annotations

from collections import namedtuple

import torch

__all__ = ["knn_points"]

_KNN = namedtuple("KNN", "dists idx knn")

_BRUTE_MAX_PAIRS = 1 << 26  # above this many (query, reference) pairs per cloud: a KD-tree
_CHUNK_PAIRS = 1 << 26      # distance-matrix entries per brute-force chunk


def _metric(a: torch.Tensor, b: torch.Tensor, norm: int) -> torch.Tensor:
    d = a - b
    return (d * d).sum(-1) if norm == 2 else d.abs().sum(-1)


def _search(q: torch.Tensor, r: torch.Tensor, k: int, norm: int) -> torch.Tensor:
    """Indices [P1, k] of the k nearest rows of ``r`` [P2, D] for each row of ``q`` [P1, D], nearest first."""
    if q.shape[0] * r.shape[0] > _BRUTE_MAX_PAIRS:
        from scipy.spatial import cKDTree
        tree = cKDTree(r.detach().to("cpu", torch.float64).numpy())
        _, idx = tree.query(q.detach().to("cpu", torch.float64).numpy(), k=k, p=norm, workers=-1)
        return torch.as_tensor(idx, dtype=torch.int64, device=q.device).reshape(q.shape[0], k)
    out = []
    qd, rd = q.detach(), r.detach()
    step = max(1, _CHUNK_PAIRS // max(r.shape[0], 1))
    for c in qd.split(step):
        d = torch.cdist(c.double(), rd.double(), p=float(norm))
        d = d.square() if norm == 2 else d
        out.append(d.topk(k, dim=1, largest=False, sorted=True).indices)
    return torch.cat(out) if out else torch.zeros((0, k), dtype=torch.int64, device=q.device)


def knn_points(p1: torch.Tensor, p2: torch.Tensor, lengths1=None, lengths2=None, norm: int = 2, K: int = 1,
               version: int = -1, return_nn: bool = False, return_sorted: bool = True):
    """See the module docstring. ``version`` is ignored; results are always sorted."""
    if p1.dim() != 3 or p2.dim() != 3 or p1.shape[0] != p2.shape[0] or p1.shape[2] != p2.shape[2]:
        raise ValueError("knn_points: p1 [N, P1, D] and p2 [N, P2, D] must share N and D")
    if norm not in (1, 2):
        raise ValueError("knn_points: norm must be 1 or 2")
    if K < 1:
        raise ValueError("knn_points: K must be positive")
    n, P1, D = p1.shape
    P2 = p2.shape[1]
    l1 = [P1] * n if lengths1 is None else [int(v) for v in lengths1]
    l2 = [P2] * n if lengths2 is None else [int(v) for v in lengths2]
    idx = torch.zeros((n, P1, K), dtype=torch.int64, device=p1.device)
    valid = torch.zeros((n, P1, K), dtype=torch.bool, device=p1.device)
    for b in range(n):
        k = min(K, l2[b])
        if l1[b] == 0 or k == 0:
            continue
        idx[b, :l1[b], :k] = _search(p1[b, :l1[b]], p2[b, :l2[b]], k, norm)
        valid[b, :l1[b], :k] = True
    nn = torch.gather(p2, 1, idx.reshape(n, P1 * K, 1).expand(n, P1 * K, D)).reshape(n, P1, K, D)
    dists = torch.where(valid, _metric(p1[:, :, None, :], nn, norm), torch.zeros((), dtype=p1.dtype, device=p1.device))
    knn = torch.where(valid[..., None], nn, torch.zeros((), dtype=p2.dtype, device=p2.device)) if return_nn else None
    return _KNN(dists=dists, idx=idx, knn=knn)
