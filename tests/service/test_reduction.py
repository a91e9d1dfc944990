"""service.reduction: the entry reduction keeps about the limit, uniformly, whatever the order of the points."""

import numpy as np

from service.reduction import ENTRY_BLOCK, entry_indices
from service.sampling import coordinate_hash


def test_small_clouds_are_kept_whole():
    assert entry_indices(np.zeros((1000, 3)), limit=1000) is None


def test_keeps_about_the_limit_spread_over_the_cloud():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (400_000, 3))
    kept = entry_indices(points, limit=50_000)
    assert abs(len(kept) - 50_000) < 1_500 and np.all(np.diff(kept) > 0)
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
    threshold = np.uint64(int(20_000 / len(points) * 2**64))
    np.testing.assert_array_equal(kept, np.flatnonzero(coordinate_hash(points - origin) < threshold))
    assert not np.array_equal(kept, entry_indices(points, limit=20_000))  # the origin does change the picks
