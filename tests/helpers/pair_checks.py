"""Checks of generated pairs shared by the data-protocol tests, and the marks that skip them without ModelNet40.

Import as ``from pair_checks import ...`` (``pythonpath`` in ``pyproject.toml``, as ``shapes``).
"""

from __future__ import annotations

import numpy as np
import pytest

from model.data import DENSE_FILE, data_dir

EXACT = 1e-5  # float32 round-off of R p + t for |p| <= 1.5

needs_modelnet = pytest.mark.skipif(
    not (data_dir() / "modelnet40_test.npz").exists(),
    reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)",
)
needs_dense = pytest.mark.skipif(
    not (data_dir() / DENSE_FILE).exists() or not (data_dir() / "modelnet40_test.npz").exists(),
    reason=f"{DENSE_FILE} or modelnet40_test.npz not found at {data_dir()} (set $MFGNET_DATA)",
)


def moved(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return points.astype(np.float64) @ R.astype(np.float64).T + t.astype(np.float64)


def check_indices(shapes: np.ndarray, pairs: dict, disjoint: bool) -> None:
    """Each source point is its shape row (unmoved, no noise), each target point R row + t; the source
    and target rows are disjoint (or, for the paper's settings, shared)."""
    for b in range(len(pairs["source"])):
        src_idx, tgt_idx = pairs["source_index"][b], pairs["target_index"][b]
        assert len(np.unique(src_idx)) == len(src_idx) and len(np.unique(tgt_idx)) == len(tgt_idx)
        np.testing.assert_array_equal(pairs["source"][b], shapes[b][src_idx])
        target = moved(shapes[b][tgt_idx], pairs["rotation"][b], pairs["translation"][b])
        assert np.abs(pairs["target"][b] - target).max() < EXACT
        shared = np.intersect1d(src_idx, tgt_idx).size
        assert shared == 0 if disjoint else shared > 0.5 * len(src_idx)

