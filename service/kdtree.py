"""Nearest-neighbour queries of the runtime: the one KD-tree that every module uses.

pykdtree (C; 1.4-2x faster queries than scipy's ``cKDTree`` on the service's 768-point clouds, 5x faster
builds) behind :class:`KDTree`, with ``cKDTree.query``'s conventions: float64 distances, int64 indices,
and where fewer than ``k`` points lie within ``distance_upper_bound`` (or the tree holds fewer than ``k``),
the missing neighbours come back as distance ``inf`` and index ``n`` (the number of points in the tree).

pykdtree spreads each query over OpenMP threads. Its OpenMP runtime is loaded with a passive wait policy
(``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets one): idle workers sleep between queries instead of
spinning, so that they take no core from the calling thread's numpy work, from ONNX Runtime, or from another
process (spinning workers made two processes registering at once each take 3.6x the time). Each query sets the
OpenMP thread count of every loaded runtime *for the calling thread* (OpenMP's thread count is a per-thread
setting) and restores it right after: :func:`query_threads` -- one thread, except for a query of at least
``SPLIT_QUERIES`` points made inside :func:`sharing_cores` (a registration, :class:`service.speculation.Helpers`),
which gets its share of the cores, and one wherever a second OpenMP runtime is loaded (torch's, on the training
side: its process-wide runtime would serve pykdtree's calls with torch's thread count, a 768-point query 1,186 us
instead of 151). The runtimes are found at the first query; one loaded after that is not set (slower queries,
same results). ``docs/decisions/0045-kd-tree-queries-on-the-free-cores.md``.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from threadpoolctl import ThreadpoolController

SPLIT_QUERIES = 400  # a query of fewer points runs on one thread: waking a second costs more than it saves
MAX_QUERY_THREADS = 2  # the most threads one query runs on (measured on 2 cores; larger teams are not)


def _import_pykdtree() -> type:
    """pykdtree's tree, its OpenMP runtime loaded (its settings read) with a passive wait policy; the environment is
    restored after, so that a runtime loaded later (torch's) keeps its own default."""
    unset = "OMP_WAIT_POLICY" not in os.environ
    if unset:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    try:
        from pykdtree.kdtree import KDTree as PyKDTree
    finally:
        if unset:
            os.environ.pop("OMP_WAIT_POLICY", None)
    return PyKDTree


_PyKDTree = _import_pykdtree()
_MISSING = np.iinfo(np.uint32).max  # pykdtree's index for a neighbour beyond the tree's size
_openmp_lock = threading.Lock()
_openmp: list | None = None  # threadpoolctl controllers of the loaded OpenMP runtimes, found once
_sharing = threading.local()  # .cores: the calling thread's share of the cores, asked at each query (unset: 1)


def openmp_runtimes() -> list:
    """The OpenMP runtimes loaded in this process (pykdtree's own; torch's where torch is loaded)."""
    global _openmp
    with _openmp_lock:
        if _openmp is None:
            _openmp = ThreadpoolController().select(user_api="openmp").lib_controllers
        return _openmp


@contextmanager
def openmp_threads(threads: int) -> Iterator[None]:
    """Every OpenMP runtime at ``threads`` threads for the calling thread while the block runs."""
    runtimes = openmp_runtimes()
    previous = [lib.get_num_threads() for lib in runtimes]
    for lib in runtimes:
        lib.set_num_threads(threads)
    try:
        yield
    finally:
        for lib, count in zip(runtimes, previous, strict=True):
            lib.set_num_threads(count)


@contextmanager
def sharing_cores(cores: Callable[[], int]) -> Iterator[None]:
    """Within the block the calling thread's large queries run on ``cores()`` threads (asked at each query, at most
    ``MAX_QUERY_THREADS``): its share of the cores at the time."""
    previous = getattr(_sharing, "cores", None)
    _sharing.cores = cores
    try:
        yield
    finally:
        _sharing.cores = previous


def query_threads(points: int) -> int:
    """The OpenMP threads of the calling thread's next query of ``points`` points: its :func:`sharing_cores` share
    for at least ``SPLIT_QUERIES`` points, else 1; 1 wherever more than one OpenMP runtime is loaded."""
    cores = getattr(_sharing, "cores", None)
    if cores is None or points < SPLIT_QUERIES or len(openmp_runtimes()) != 1:
        return 1
    return max(1, min(int(cores()), MAX_QUERY_THREADS))


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
        with openmp_threads(query_threads(len(queries))):
            dist, idx = self._tree.query(queries, k=int(k), distance_upper_bound=distance_upper_bound)
        missing = idx == _MISSING
        index = idx.astype(np.int64)
        if missing.any():
            dist[missing], index[missing] = np.inf, self.n
        return dist, index
