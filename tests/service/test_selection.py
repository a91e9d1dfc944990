"""service.selection.top_k: the largest values, largest first, ties by position."""

import numpy as np

from service.selection import top_k


def test_top_k_matches_a_full_sort_ties_by_position():
    rng = np.random.default_rng(4)
    for values in (rng.normal(size=250_000), np.rint(rng.normal(scale=3.0, size=250_000)), rng.normal(size=40),
                   np.zeros(1000)):
        for count in (1, 100, 200):
            expected = np.lexsort((np.arange(values.size), -values))[:count]  # value descending, then index
            np.testing.assert_array_equal(top_k(values, count), expected)


def test_top_k_counts_nan_as_the_smallest_value():
    values = np.random.default_rng(5).normal(size=5000)
    values[::3] = np.nan  # a damaged model's scores
    for count in (100, 2000):
        expected = np.lexsort((np.arange(values.size), -values))[:count]  # NaN sorts last
        np.testing.assert_array_equal(top_k(values, count), expected)
        assert not np.isnan(values[top_k(values, count)]).any()  # 3,333 values are not NaN
