"""service.kdtree.KDTree: scipy's cKDTree conventions on pykdtree, one OpenMP thread per querying thread
or a registration's share of the cores, and a runtime that waits passively."""

from __future__ import annotations

import os
import subprocess
import sys
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


def _recording_tree(points: np.ndarray, runtimes: list) -> tuple[KDTree, list[list[int]]]:
    """A real tree whose queries note the OpenMP thread counts they run under."""
    tree = KDTree(points)
    pykdtree_query = tree._tree.query
    during: list[list[int]] = []

    def recording_query(*args, **kwargs):  # the real query, noting the thread counts it runs under
        during.append([lib.get_num_threads() for lib in runtimes])
        return pykdtree_query(*args, **kwargs)

    tree._tree = type("Recording", (), {"query": staticmethod(recording_query)})()
    return tree, during


def _runtimes() -> list:
    runtimes = kdtree.openmp_runtimes()
    if not runtimes:
        pytest.skip("no OpenMP runtime is loaded (a pykdtree built without OpenMP): nothing to set")
    return runtimes


def test_queries_run_one_openmp_thread_and_restore_it() -> None:
    """Outside a registration every OpenMP runtime runs one thread for the querying thread during a query;
    afterwards that thread and every other keep their own count."""
    runtimes = _runtimes()
    points = np.random.default_rng(2).random((kdtree.SPLIT_QUERIES, 3))
    tree, during = _recording_tree(points, runtimes)
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


def test_a_large_query_inside_sharing_cores_runs_on_its_share() -> None:
    """Inside ``sharing_cores`` a query of at least ``SPLIT_QUERIES`` points runs on the share asked at that moment
    (at most ``MAX_QUERY_THREADS``), a smaller one on one thread; with more than one OpenMP runtime loaded (torch's),
    every query on one. The neighbours are the same either way, and the count is restored after the block."""
    runtimes = _runtimes()
    points = np.random.default_rng(3).random((kdtree.SPLIT_QUERIES, 3))
    tree, during = _recording_tree(points, runtimes)
    one_runtime = len(runtimes) == 1
    share = [2]
    outside = tree.query(points, k=2)
    during.clear()
    with kdtree.sharing_cores(lambda: share[0]):
        inside = tree.query(points, k=2)
        tree.query(points[: kdtree.SPLIT_QUERIES - 1], k=2)
        share[0] = 1  # a second registration started
        tree.query(points, k=2)
        share[0] = 16
        tree.query(points, k=2)
    tree.query(points, k=2)
    expected = [2, 1, 1, kdtree.MAX_QUERY_THREADS, 1] if one_runtime else [1] * 5
    assert during == [[n] * len(runtimes) for n in expected]
    np.testing.assert_array_equal(inside[1], outside[1])
    np.testing.assert_array_equal(inside[0], outside[0])


def test_pykdtree_runtime_waits_passively_and_the_environment_is_left_as_it_was() -> None:
    """Loaded by ``service.kdtree``, pykdtree's OpenMP runtime does not spin between queries (libgomp reports a spin
    count of 0); ``OMP_WAIT_POLICY`` is not left set, so a runtime loaded after it keeps its own default."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env["OMP_DISPLAY_ENV"] = "VERBOSE"  # libgomp prints its settings to stderr when it loads
    code = "import os, service.kdtree; print(os.environ.get('OMP_WAIT_POLICY'))"
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    if "GOMP_SPINCOUNT" not in run.stderr:
        pytest.skip("pykdtree's OpenMP runtime is not libgomp: no settings to read")
    assert "GOMP_SPINCOUNT = '0'" in run.stderr
    assert run.stdout.strip() == "None"
