"""service.reduction: the entry reduction keeps the limit, uniformly, whatever the order of the points; a stack of
identical points counts once."""

import numpy as np

from service.checks import MIN_POINTS
from service.reduction import ENTRY_BLOCK, entry_indices
from service.sampling import coordinate_hash, lowest_distinct


def test_small_clouds_are_kept_whole():
    assert entry_indices(np.zeros((1000, 3)), limit=1000) is None


def test_keeps_the_limit_spread_over_the_cloud():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (400_000, 3))
    kept = entry_indices(points, limit=50_000)
    assert len(kept) == 50_000 and np.all(np.diff(kept) > 0)
    octants = np.bincount(((points[kept] > 0) * [1, 2, 4]).sum(1), minlength=8)  # [8] uniform: ~6,250 each
    assert octants.min() > 5_800 and octants.max() < 6_700


def test_independent_of_point_order():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(30_000, 3))
    order = rng.permutation(len(points))
    a = points[entry_indices(points, limit=5_000)]
    b = points[order][entry_indices(points[order], limit=5_000)]
    assert np.array_equal(np.unique(a, axis=0), np.unique(b, axis=0))


def test_blocks_hash_the_rows_about_the_origin():
    """Hashed block by block about ``origin``: the same rows as hashing the whole moved cloud at once."""
    points = np.random.default_rng(2).normal(size=(3 * ENTRY_BLOCK + 123, 3)) + np.array([40.0, -7.0, 3.0])
    origin = points[::97].mean(axis=0)
    kept = entry_indices(points, limit=20_000, origin=origin)
    np.testing.assert_array_equal(kept, np.sort(lowest_distinct(coordinate_hash(points - origin), 20_000)))
    assert not np.array_equal(kept, entry_indices(points, limit=20_000))  # the origin does change the picks


def test_a_stack_of_identical_points_counts_once():
    """A sensor's invalid returns stacked at one place neither crowd the surface out nor, dropped whole, empty it."""
    rng = np.random.default_rng(3)
    surface = rng.uniform(-1, 1, (60_000, 3))
    for stack_at in (np.zeros(3), surface[0]):
        points = np.concatenate([np.repeat(stack_at[None], 300_000, axis=0), surface])
        kept = points[entry_indices(points, limit=20_000)]
        assert len(kept) == 20_000 and len(np.unique(kept, axis=0)) == 20_000


def test_a_cloud_of_few_distinct_points_keeps_each_once_and_at_least_the_minimum_rows():
    rng = np.random.default_rng(4)
    few = rng.normal(size=(500, 3))
    points = few[rng.integers(0, 500, 150_000)]  # 500 distinct points, 300 rows each
    kept = entry_indices(points, limit=20_000)
    assert len(kept) == 500 and len(np.unique(points[kept], axis=0)) == 500
    for distinct in (1, 7):
        points = few[:distinct][rng.integers(0, distinct, 150_000)]
        kept = entry_indices(points, limit=20_000)
        assert len(kept) == MIN_POINTS and len(np.unique(kept)) == MIN_POINTS
        assert len(np.unique(points[kept], axis=0)) == distinct
