"""A range image's viewing axis and free space (service.free_space), on synthetic scans of a bumpy surface."""

from __future__ import annotations

import numpy as np

from service.free_space import RANGE_IMAGE_CORRELATION, free_space_share, pose_free_space, range_view
from service.stages.free_space import RELIABLE_FREE_SPACE


def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.8 * np.sin(3.0 * x) * np.cos(2.0 * y)  # slopes up to about 70 deg


def pixel_grid_scan(rotation: np.ndarray, pixels: int = 160) -> np.ndarray:
    """``[pixels**2, 3]``: the surface ``z = height(x, y)`` sampled on a regular grid seen along z (an orthographic
    range image: its density on the surface falls with the cosine of the incidence angle), then turned by
    ``rotation [3, 3]``."""
    x, y = np.meshgrid(np.linspace(-1, 1, pixels), np.linspace(-1, 1, pixels))
    points = np.stack([x.ravel(), y.ravel(), height(x, y).ravel()], axis=1)
    return points @ rotation.T


def turn(axis: np.ndarray, degrees: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def test_a_range_image_gives_its_viewing_axis() -> None:
    rotation = turn(np.array([1.0, 2.0, 0.5]), 40.0)
    view = range_view(pixel_grid_scan(rotation))
    assert view is not None and view.correlation >= RANGE_IMAGE_CORRELATION
    assert abs(view.axis @ rotation[:, 2]) > np.cos(np.radians(5.0))  # the turned z axis, up to its sign


def test_uniform_samples_of_the_surface_are_no_range_image() -> None:
    """Points spread evenly over the surface (as a mesh sampler or a fused fragment's voxels give them) have a
    density that no viewing direction explains."""
    rng = np.random.default_rng(0)
    dense = pixel_grid_scan(np.eye(3), pixels=400)
    gy, gx = np.gradient(dense[:, 2].reshape(400, 400), 2 / 399)
    cos = 1 / np.sqrt(1 + gx.ravel() ** 2 + gy.ravel() ** 2)  # [N] of the surface normal and the z axis
    uniform = dense[rng.random(len(dense)) < cos.min() / cos]  # each kept against its cos: even per unit of surface
    assert len(uniform) > 4000
    assert range_view(uniform) is None


def test_the_truth_leaves_free_space_empty_and_a_half_turn_does_not() -> None:
    target = pixel_grid_scan(np.eye(3))
    source_to_target = turn(np.array([0.3, -1.0, 0.2]), 25.0)  # the source scan: the surface turned away from z
    source = pixel_grid_scan(np.eye(3), pixels=150) @ source_to_target  # the same surface in the source's frame
    views = (range_view(source), range_view(target))
    assert views[0] is not None and views[1] is not None
    R, t = source_to_target, np.zeros(3)
    assert pose_free_space(*views, source, target, R, t) < 0.01
    half = turn(np.array([1.0, 0.0, 0.0]), 180.0)  # the right pose turned half a turn about the target's x axis
    share = pose_free_space(*views, source, target, half @ R, half @ t)
    assert share > RELIABLE_FREE_SPACE, share


def test_points_hidden_behind_what_the_sensor_saw_are_no_evidence() -> None:
    target = pixel_grid_scan(np.eye(3))
    view = range_view(target)
    assert view is not None
    behind = target[::7] - 0.5 * view.axis  # the same surface moved along the axis: behind it from one side
    assert free_space_share(view, behind) == 0.0
    beside = target[::7] + np.array([5.0, 0.0, 0.0])  # cells the sensor never saw
    assert free_space_share(view, beside) == 0.0
