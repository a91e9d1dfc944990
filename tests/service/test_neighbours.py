"""The runtime's k-NN graph (the encoder's input) against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from service.neighbours import knn_graph


def brute_force_sets(cloud: np.ndarray, k: int) -> list[set[int]]:
    d2 = ((cloud[:, None].astype(np.float64) - cloud[None]) ** 2).sum(-1)  # [N, N]
    return [set(row) for row in np.argsort(d2, axis=1, kind="stable")[:, :k].tolist()]


@pytest.mark.parametrize("n", [12, 100, 768])
def test_knn_graph_matches_brute_force_and_includes_each_point(n: int) -> None:
    clouds = np.random.default_rng(n).normal(size=(2, n, 3)).astype(np.float32)
    graph = knn_graph(clouds, 12)
    assert graph.shape == (2, n, 12) and graph.dtype == np.int64
    for cloud, rows in zip(clouds, graph, strict=True):
        assert [set(r) for r in rows.tolist()] == brute_force_sets(cloud, 12)
        assert all(i in set(r) for i, r in enumerate(rows.tolist()))


def test_knn_graph_is_rotation_invariant() -> None:
    cloud = np.random.default_rng(1).normal(size=(1, 300, 3))
    angle = np.radians(70.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    a, b = knn_graph(cloud, 12), knn_graph(cloud @ R.T, 12)
    assert np.array_equal(np.sort(a, axis=-1), np.sort(b, axis=-1))


@pytest.mark.parametrize(("shape", "k", "message"), [((5, 3), 4, "points must be"), ((1, 5, 2), 4, "points must be"),
                                                     ((1, 5, 3), 12, "at least k = 12")])
def test_knn_graph_rejects_bad_shapes(shape: tuple[int, ...], k: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        knn_graph(np.zeros(shape), k)
