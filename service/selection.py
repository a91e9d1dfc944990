"""Selection of the largest values of an array, in a defined order: the network's keypoints, the translation
search's best shifts."""

from __future__ import annotations

import numpy as np

SAMPLE_STRIDE = 16  # top_k(): every SAMPLE_STRIDE-th value bounds the threshold


def top_k(values: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` largest of ``values [V]``, largest first (ties: lower index first; NaN counts as the
    smallest value).

    Every ``SAMPLE_STRIDE``-th value gives a threshold that at least ``count`` values reach (the ``count``-th
    largest of the sample), so only the values at or above it are selected and sorted: the same result as a sort of
    all ``V`` at a fraction of its cost on a correlation grid of ~250,000 shifts.
    """
    if values.size <= count:
        chosen = np.arange(values.size)
    else:
        sample = values[::SAMPLE_STRIDE]
        floor = np.partition(sample, sample.size - count)[sample.size - count] if sample.size > count else values.min()
        chosen = np.flatnonzero(values >= floor)  # [C], ascending: C >= count unless NaNs took the sample's top
        if chosen.size < count:
            chosen = np.arange(values.size)
    ranked = chosen[np.lexsort((chosen, -values[chosen]))]  # value descending, then index ascending
    return ranked[:count]
