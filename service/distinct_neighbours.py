"""Neighbourhoods that count each place once, for the PCA normals (:func:`service.icp.target_normals`).

A cloud whose rows repeat points (mesh vertices written once per face, merged scans, tiles that overlap) fills a
point's nearest rows with copies: 12 nearest rows can be 2-3 places, a line or a 3-point plane, and the normal of
a dense target turns by degrees. Copies are found in the neighbourhood query the normal needs anyway (two of its
rows at the same distance and the same coordinates), so a cloud without them pays one comparison per row; only the
rows whose neighbourhoods hold copies take their neighbours from the cloud's distinct points
(``docs/decisions/0124-copies-found-where-a-normal-is-computed.md``).
"""

from __future__ import annotations

import numpy as np

from service.kdtree import KDTree
from service.per_instance_cache import per_instance_cached_property
from service.sampling import coordinate_hash, distinct_rows


def copied_neighbourhoods(distances: np.ndarray, hoods: np.ndarray) -> np.ndarray:
    """``[A]`` bool: which neighbourhoods ``hoods [A, k, 3]`` (sorted by ``distances [A, k]``) hold one place twice.
    Copies lie at equal distances, so only rows with a tie are looked at: those whose coordinates' hashes
    (:func:`service.sampling.coordinate_hash`) repeat, then coordinate by coordinate (a fused fragment on a millimetre
    grid ties in a third of its rows)."""
    tied = np.flatnonzero((np.diff(distances, axis=1) == 0).any(axis=1))  # [T]
    hashes = np.sort(coordinate_hash(hoods[tied].reshape(-1, 3)).reshape(len(tied), hoods.shape[1]), axis=1)  # [T, k]
    suspects = tied[(hashes[:, 1:] == hashes[:, :-1]).any(axis=1)]  # [S]
    around = hoods[suspects]  # [S, k, 3]
    same = (around[:, :, None, :] == around[:, None, :, :]).all(axis=3)  # [S, k, k]
    copied = np.zeros(len(hoods), dtype=bool)
    copied[suspects] = np.triu(same, k=1).any(axis=(1, 2))
    return copied


class DistinctPoints:
    """A cloud's distinct points (each coordinate's first row, :func:`service.sampling.distinct_rows`) and their
    KD-tree, built when a neighbourhood with copies first asks: a surface whose normals are computed a few rows at a
    time hashes its cloud once."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points  # [M, 3] float64, copies included

    @per_instance_cached_property
    def distinct(self) -> tuple[np.ndarray, KDTree]:
        """``[D, 3]`` the distinct points and their tree."""
        points = self.points[distinct_rows(self.points, np.arange(len(self.points)))]
        return points, KDTree(points)

    def neighbourhoods(self, at: np.ndarray, k: int) -> np.ndarray | None:
        """``[C, k, 3]``: the ``k`` distinct points nearest each of ``at [C, 3]``, or ``None`` where the cloud holds
        fewer than ``k`` distinct points."""
        points, tree = self.distinct
        if len(points) < k:
            return None
        return points[tree.query(at, k=k)[1]]
