"""PCA normals count each place once: rows that repeat a point (mesh vertices written once per face, merged scans)
are found in the normal's own neighbourhood query, and those neighbourhoods come from the distinct points."""

from __future__ import annotations

import numpy as np
from shapes import range_patch

from service.distinct_neighbours import DistinctPoints, copied_neighbourhoods
from service.icp import LazySurface, Surface, target_normals
from service.kdtree import KDTree


def patch_with_copies(copies: int, every: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A noisy range patch of 3,000 points, and the same patch with every ``every``-th row written ``copies`` times
    (the copies appended, so that the first 3,000 rows are the patch itself)."""
    points = range_patch(3_000, seed=4) + np.random.default_rng(5).normal(0.0, 0.002, (3_000, 3))
    return points, np.vstack([points, *[points[::every]] * (copies - 1)])


def test_copies_among_a_points_neighbours_are_found_and_ties_between_places_are_not():
    grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), [0.0]), axis=-1).reshape(-1, 3)  # [25, 3]
    with_copy = np.vstack([grid, grid[12]])  # the centre twice
    for cloud, expected in ((grid, False), (with_copy, True)):
        distances, rows = KDTree(cloud).query(cloud[12:13], k=9)  # the centre: 4 neighbours at 1, 4 at sqrt(2)
        assert (np.diff(distances, axis=1) == 0).any()  # tied either way
        assert copied_neighbourhoods(distances, cloud[rows]).tolist() == [expected]


def test_normals_of_a_cloud_with_copies_are_those_of_its_distinct_points():
    """A third of the rows written 6 times: their neighbours' 12 nearest rows were a handful of places, and the
    normals turned; they are now the normals of the cloud without copies, bit for bit."""
    points, copied = patch_with_copies(6)
    expected, expected_defined = target_normals(points)
    normals, defined = target_normals(copied)
    assert np.array_equal(normals[:3_000], expected) and np.array_equal(defined[:3_000], expected_defined)
    lazy = LazySurface(copied, KDTree(copied))
    rows = np.arange(0, 3_000, 7)
    assert np.array_equal(lazy.at(rows)[0], expected[rows])
    assert np.array_equal(Surface.of(copied).normals[:3_000], expected)


def test_a_cloud_without_copies_is_never_hashed_for_them():
    points, _ = patch_with_copies(6)
    lazy = LazySurface(points, KDTree(points))
    lazy.at(np.arange(3_000))
    assert "distinct" not in vars(lazy.distinct)


def test_a_cloud_of_fewer_distinct_points_than_a_neighbourhood_keeps_its_rows():
    """40 places, each written 3 times, and neighbourhoods of 60: the copies stay, the normals are computed."""
    places = range_patch(40, seed=6)
    cloud = np.repeat(places, 3, axis=0)  # [120, 3]
    assert DistinctPoints(cloud).neighbourhoods(places[:1], 60) is None
    normals = target_normals(cloud, neighbours=60)[0]
    assert normals.shape == (120, 3) and np.isfinite(normals).all()
    assert np.array_equal(DistinctPoints(cloud).neighbourhoods(places[:1], 12)[0], places[KDTree(places).query(
        places[:1], k=12)[1][0]])
