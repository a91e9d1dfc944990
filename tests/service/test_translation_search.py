"""service.translation_search: occupancy cross-correlation finds the translation of a slid partial view."""

import numpy as np
from shapes import room_scene

from service.translation_search import column_bounds, occupancy, translation_candidates


def test_occupancy_marks_the_cells_points_fall_in():
    grid = occupancy(np.array([[0.05, 0.05, 0.05], [0.25, 0.05, 0.05], [9.0, 0.0, 0.0]]), np.zeros(3), 0.1, (4, 4, 4))
    assert grid.sum() == 2 and grid[0, 0, 0] == 1 and grid[2, 0, 0] == 1  # the point outside the grid is ignored


def test_occupancy_is_the_cell_of_each_point_inside_the_grid_one_by_one():
    rng = np.random.default_rng(4)
    points = rng.uniform(-1.5, 6.5, size=(5000, 3))  # [N, 3] about a third outside the grid, on every side
    points[:3] = [[1e30, 0.5, 0.5], [-1e30, 0.5, 0.5], [0.5, 0.5, 1e18]]  # far beyond any integer cell
    origin, cell, shape = np.array([0.0, -0.5, 0.25]), 0.37, (13, 17, 11)
    expected = np.zeros(shape, np.float32)
    for point in points:
        index = np.floor((point - origin) / cell)
        if np.all(index >= 0) and np.all(index < shape):
            expected[tuple(index.astype(int))] = 1.0
    assert 0 < expected.sum() < len(points)
    assert np.array_equal(occupancy(points, origin, cell, shape), expected)
    assert np.array_equal(occupancy(points.astype(np.float32), origin, cell, shape),
                          occupancy(points.astype(np.float32).astype(np.float64), origin, cell, shape))


def test_finds_the_translation_of_overlapping_partial_views():
    rng = np.random.default_rng(0)
    scene = room_scene(rng)
    source = scene[scene[:, 0] < 3.2]  # two partial views that overlap on x in [0.8, 3.2]
    target = scene[scene[:, 0] > 0.8]
    true_t = np.array([0.7, -0.4, 0.2])
    moved = source - true_t  # the caller's source: source = moved + true_t
    candidates = translation_candidates(moved, target)
    cell = 4.7 / 32
    assert candidates.shape[1] == 3 and len(candidates) >= 2
    # the most overlap is not always the right place (a slide along the floor and a wall overlaps more), so the
    # contract is a short list that holds the right translation; the registrar ranks them by their refined fit
    assert np.abs(candidates - true_t).max(axis=1).min() <= 1.5 * cell, candidates


def test_identity_when_clouds_coincide():
    rng = np.random.default_rng(1)
    scene = room_scene(rng, 2000)
    assert np.abs(translation_candidates(scene, scene)[0]).max() < 1e-9


def test_candidates_are_distinct_basins():
    rng = np.random.default_rng(2)
    scene = room_scene(rng, 2000)
    candidates = translation_candidates(scene, scene + np.array([0.3, 0.0, 0.0]), count=4)
    cell = 4.3 / 32
    gaps = np.abs(candidates[:, None] - candidates[None]).max(-1) + np.eye(len(candidates)) * 99
    assert gaps.min() > 2 * cell - 1e-9


def test_column_bounds_are_the_per_axis_minimum_and_maximum():
    points = np.random.default_rng(3).normal(size=(5000, 3)) * [1.0, 10.0, 0.1]
    low, high = column_bounds(points)
    np.testing.assert_array_equal(low, points.min(axis=0))
    np.testing.assert_array_equal(high, points.max(axis=0))
