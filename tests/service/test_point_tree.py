"""``service.point_tree.PointTree`` answers like ``scipy.spatial.cKDTree`` (the interface it replaces)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.point_tree import PointTree


@pytest.mark.parametrize("k", [1, 12])
def test_nearest_neighbours_equal_scipys(k: int) -> None:
    rng = np.random.default_rng(k)
    points, queries = rng.normal(size=(768, 3)), rng.normal(size=(500, 3))
    dist, idx = PointTree(points).query(queries, k=k)
    ref_dist, ref_idx = cKDTree(points).query(queries, k=k)
    assert idx.dtype == np.intp and idx.shape == ref_idx.shape
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_allclose(dist, ref_dist, rtol=1e-12, atol=1e-15)


def test_neighbours_beyond_the_bound_or_the_tree_come_back_as_inf_and_the_tree_size() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    tree = PointTree(points)
    dist, idx = tree.query(np.array([[0.1, 0.0, 0.0], [5.0, 5.0, 5.0]]), k=1, distance_upper_bound=0.5)
    np.testing.assert_array_equal(idx, [0, 3])
    assert dist[0] == pytest.approx(0.1) and dist[1] == np.inf
    dist, idx = tree.query(np.zeros((1, 3)), k=5)  # more neighbours than points
    np.testing.assert_array_equal(idx, [[0, 1, 2, 3, 3]])
    assert np.isinf(dist[0, 3:]).all()


def test_float32_empty_and_strided_queries_are_accepted() -> None:
    rng = np.random.default_rng(0)
    wide = rng.normal(size=(50, 6))
    tree = PointTree(wide[:, :3])  # not contiguous
    dist, idx = tree.query(wide[:, :3].astype(np.float32), k=1)
    np.testing.assert_array_equal(idx, np.arange(50))
    assert dist.max() < 1e-6
    dist, idx = tree.query(np.zeros((0, 3)), k=1)
    assert dist.shape == (0,) and idx.shape == (0,)


@pytest.mark.parametrize("shape", [(0, 3), (5, 2), (3,)])
def test_rejects_an_empty_or_misshapen_cloud(shape) -> None:
    with pytest.raises(ValueError, match=r"points \[M, 3\]"):
        PointTree(np.zeros(shape))


_THREAD_PROBE = """
import os, numpy as np
before = len(os.listdir("/proc/self/task"))
from service.point_tree import PointTree
rng = np.random.default_rng(0)
PointTree(rng.normal(size=(20000, 3))).query(rng.normal(size=(20000, 3)), k=4)
print(before, len(os.listdir("/proc/self/task")), os.environ.get("OMP_NUM_THREADS", "unset"))
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads through Linux's /proc")
@pytest.mark.parametrize("omp", [None, "2"])
def test_queries_start_no_openmp_threads_and_leave_the_environment_alone(omp: str | None) -> None:
    """OpenMP threads beside ONNX Runtime's made refinement 1.8x slower; the library runs single-threaded."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    if omp is not None:
        env["OMP_NUM_THREADS"] = omp
    out = subprocess.run([sys.executable, "-c", _THREAD_PROBE], env=env, capture_output=True, text=True, check=True)
    before, after, seen = out.stdout.split()
    assert int(after) == int(before), "the query started worker threads"
    assert seen == (omp or "unset")
