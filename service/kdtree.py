"""Nearest-neighbour queries of the runtime: the one KD-tree that every module uses.

pykdtree (C; 1.4-2x faster queries than scipy's ``cKDTree`` on the service's 768-point clouds, 5x faster
builds) behind :class:`KDTree`, with ``cKDTree.query``'s conventions: float64 distances, int64 indices,
and where fewer than ``k`` points lie within ``distance_upper_bound`` (or the tree holds fewer than ``k``),
the missing neighbours come back as distance ``inf`` and index ``n`` (the number of points in the tree).

pykdtree spreads each query over OpenMP threads. Between the many short queries of an ICP idle OpenMP
workers spin and slow the calling thread's numpy work on a 2-core machine; and once torch is loaded (the
training side), its process-wide OpenMP runtime serves pykdtree's calls with torch's thread count (a
768-point query: 1,186 us instead of 151 with one thread; ``docs/DESIGN.md``, "Nearest neighbours"). So
each query runs with every loaded OpenMP runtime limited to one thread *for the calling thread* (OpenMP's
thread count is a per-thread setting), restored right after: other threads, and torch's own work
between queries, keep their threads. The runtimes are found at the first query; one loaded after that
is not limited (slower queries, same results).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
from pykdtree.kdtree import KDTree as _PyKDTree
from threadpoolctl import ThreadpoolController

_MISSING = np.iinfo(np.uint32).max  # pykdtree's index for a neighbour beyond the tree's size
_openmp_lock = threading.Lock()
_openmp: list | None = None  # threadpoolctl controllers of the loaded OpenMP runtimes, found once


def openmp_runtimes() -> list:
    """The OpenMP runtimes loaded in this process (pykdtree's own; torch's where torch is loaded)."""
    global _openmp
    with _openmp_lock:
        if _openmp is None:
            _openmp = ThreadpoolController().select(user_api="openmp").lib_controllers
        return _openmp


@contextmanager
def one_openmp_thread() -> Iterator[None]:
    """Every OpenMP runtime at one thread for the calling thread while the block runs."""
    runtimes = openmp_runtimes()
    previous = [lib.get_num_threads() for lib in runtimes]
    for lib in runtimes:
        lib.set_num_threads(1)
    try:
        yield
    finally:
        for lib, threads in zip(runtimes, previous, strict=True):
            lib.set_num_threads(threads)


class KDTree:
    """A KD-tree over ``points [M, 3]`` (copied as float64) answering k-nearest-neighbour queries."""

    __slots__ = ("_tree", "n")

    def __init__(self, points: np.ndarray):
        data = np.ascontiguousarray(points, dtype=np.float64)
        if data.ndim != 2 or data.shape[0] == 0:
            raise ValueError(f"a KD-tree needs points [M, D] with M >= 1, got {data.shape}")
        self._tree = _PyKDTree(data)
        self.n = data.shape[0]

    def query(
        self, points: np.ndarray, k: int = 1, distance_upper_bound: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest tree points of each of ``points [Q, D]``, nearest first: distances and indices,
        ``[Q]`` each for ``k = 1``, else ``[Q, k]``; neighbours farther than ``distance_upper_bound`` (or
        beyond the tree's size) are ``inf`` / ``n``, as in ``scipy.spatial.cKDTree.query``."""
        queries = np.ascontiguousarray(points, dtype=np.float64)
        with one_openmp_thread():
            dist, idx = self._tree.query(queries, k=int(k), distance_upper_bound=distance_upper_bound)
        missing = idx == _MISSING
        index = idx.astype(np.int64)
        if missing.any():
            dist[missing], index[missing] = np.inf, self.n
        return dist, index
