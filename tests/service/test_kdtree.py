"""service.kdtree.KDTree: scipy's cKDTree conventions on pykdtree, one OpenMP thread per querying thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service import kdtree
from service.kdtree import KDTree


def _brute_force(tree_points: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    dist = np.linalg.norm(queries[:, None] - tree_points[None], axis=2)  # [Q, M]
    idx = np.argsort(dist, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(dist, idx, axis=1), idx


@pytest.mark.parametrize("k", [1, 5, 12])
def test_nearest_neighbours_equal_brute_force(k: int) -> None:
    rng = np.random.default_rng(k)
    points, queries = rng.normal(size=(500, 3)), rng.normal(size=(200, 3))
    dist, idx = KDTree(points).query(queries, k=k)
    want_dist, want_idx = _brute_force(points, queries, k)
    assert dist.dtype == np.float64 and idx.dtype == np.int64
    assert dist.shape == idx.shape == ((200,) if k == 1 else (200, k))
    np.testing.assert_array_equal(idx.reshape(200, k), want_idx)
    np.testing.assert_allclose(dist.reshape(200, k), want_dist, rtol=1e-12, atol=1e-12)


def test_misses_follow_scipy() -> None:
    """Beyond ``distance_upper_bound``, and beyond the tree's size: ``inf`` and index ``n``, as cKDTree."""
    rng = np.random.default_rng(0)
    points, queries = rng.random((40, 3)), rng.random((30, 3)) * 2.0
    for k, bound in ((1, 0.1), (4, 0.2), (50, None)):
        got = KDTree(points).query(queries, k=k, distance_upper_bound=bound)
        want = cKDTree(points).query(queries, k=k, distance_upper_bound=np.inf if bound is None else bound)
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12)
    assert np.isinf(got[0][:, 40:]).all() and (got[1][:, 40:] == 40).all()


def test_inputs_any_float_layout_and_empty_queries() -> None:
    points = np.random.default_rng(1).random((64, 3))
    tree = KDTree(points.astype(np.float32))
    dist, idx = tree.query(points[::2].astype(np.float32), k=1)  # a strided float32 view
    assert idx.tolist() == list(range(0, 64, 2)) and dist.max() < 1e-6
    assert [a.shape for a in tree.query(np.empty((0, 3)), k=1)] == [(0,), (0,)]
    assert [a.shape for a in tree.query(np.empty((0, 3)), k=3)] == [(0, 3), (0, 3)]
    with pytest.raises(ValueError, match="M >= 1"):
        KDTree(np.empty((0, 3)))


def test_queries_run_one_openmp_thread_and_restore_it() -> None:
    """During a query every OpenMP runtime runs one thread for the querying thread; afterwards that thread
    and every other keep their own count."""
    runtimes = kdtree.openmp_runtimes()
    if not runtimes:
        pytest.skip("no OpenMP runtime is loaded (a pykdtree built without OpenMP): nothing to limit")
    points = np.random.default_rng(2).random((256, 3))
    tree = KDTree(points)
    pykdtree_query = tree._tree.query
    during: list[list[int]] = []

    def recording_query(*args, **kwargs):  # the real query, noting the thread counts it runs under
        during.append([lib.get_num_threads() for lib in runtimes])
        return pykdtree_query(*args, **kwargs)

    tree._tree = type("Recording", (), {"query": staticmethod(recording_query)})()
    outcome: dict[str, list[int]] = {}

    def query_in_thread() -> None:
        for lib in runtimes:
            lib.set_num_threads(2)
        tree.query(points, k=3)
        outcome["after"] = [lib.get_num_threads() for lib in runtimes]

    before_here = [lib.get_num_threads() for lib in runtimes]
    worker = threading.Thread(target=query_in_thread)
    worker.start()
    worker.join()
    assert during == [[1] * len(runtimes)]
    assert outcome["after"] == [2] * len(runtimes)
    assert [lib.get_num_threads() for lib in runtimes] == before_here
