"""k-nearest-neighbour graph of the encoder's input, computed in the runtime (not in the graph).

A KD-tree build and query cost ~1.5 ms per 768-point cloud here (:class:`service.kdtree.KDTree`, k = 12;
scipy's ``cKDTree`` ~2.3 ms), less than the in-graph version (an ``[N, N]`` distance matrix and TopK,
~3.5 ms per cloud) and
O(N log N) instead of O(N^2); the graph is rotation invariant, so a batch of rotated copies of one
cloud (the rotation search) shares one.
"""

from __future__ import annotations

import numpy as np

from service.kdtree import KDTree


def knn_graph(points: np.ndarray, k: int) -> np.ndarray:
    """Indices ``[B, N, k]`` (int64) of the k nearest points of each point, itself included.

    ``points`` is ``[B, N, 3]``; each cloud gets its own tree. The order within a row does not
    matter to the encoder (it takes a maximum over the neighbours); exact distance ties may pick
    either point.
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be [B, N, 3], got {points.shape}")
    B, N, _ = points.shape
    if k > N:
        raise ValueError(f"a cloud needs at least k = {k} points for the neighbour graph, got {N}")
    out = np.empty((B, N, k), dtype=np.int64)
    for b in range(B):
        cloud = points[b].astype(np.float64)
        out[b] = KDTree(cloud).query(cloud, k=k)[1]
    return out
