"""Nearest-neighbour queries of the runtime: pykdtree's KD-tree behind scipy ``cKDTree``'s interface.

On 768-point clouds a pykdtree query is 1.5-2x faster than ``cKDTree`` on one thread, and refinement
runs one or two queries per ICP update (``docs/DESIGN.md``, "Nearest neighbours"). pykdtree
parallelises its queries with OpenMP, and its threads then fight ONNX Runtime's and numpy's for the
cores: with two OpenMP threads a registration's refinement took 1.8x as long as with scipy, with one
thread 0.74x. So its OpenMP runtime (a copy private to the pykdtree wheel) is loaded with one thread,
whatever ``OMP_NUM_THREADS`` says; the variable is restored right after, so nothing else sees a change.
"""

from __future__ import annotations

import os

import numpy as np


def _load_single_threaded():
    """``pykdtree.kdtree.KDTree`` with its OpenMP runtime initialised for one thread (libgomp reads
    ``OMP_NUM_THREADS`` once, when the library is loaded by this import)."""
    saved = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        from pykdtree.kdtree import KDTree
    finally:
        if saved is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = saved
    return KDTree


KDTree = _load_single_threaded()


class PointTree:
    """A KD-tree of ``points [M, 3]`` (float64) answering :meth:`query` like ``scipy.spatial.cKDTree``."""

    def __init__(self, points: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)  # [M, 3]
        if self.points.ndim != 2 or self.points.shape[1] != 3 or len(self.points) == 0:
            raise ValueError(f"a point tree needs points [M, 3] with M >= 1, got {self.points.shape}")
        self.n = len(self.points)
        self._tree = KDTree(self.points)

    def query(
        self, queries: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices of the ``k`` nearest tree points of each of ``queries [Q, 3]``.

        Shapes ``[Q]`` for ``k == 1``, else ``[Q, k]`` (nearest first); float64 distances, ``np.intp``
        indices. A neighbour farther than ``distance_upper_bound`` (or missing, ``k > M``) comes back
        as distance ``inf`` and index ``M``, as in scipy.
        """
        queries = np.ascontiguousarray(queries, dtype=np.float64)
        dist, idx = self._tree.query(queries, k=k, distance_upper_bound=distance_upper_bound)
        idx = idx.astype(np.intp)
        missing = (idx >= self.n) | ~np.isfinite(dist)  # pykdtree: index M (bound) or 2^32 - 1 (k > M)
        idx[missing], dist[missing] = self.n, np.inf
        return dist, idx
