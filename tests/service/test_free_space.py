"""A range image's viewing axis and free space (service.free_space), on synthetic scans of a bumpy surface; which doubts
the free-space stage settles."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np

from service.free_space import RANGE_IMAGE_CORRELATION, free_space_share, pose_free_space, range_view
from service.stages.free_space import RELIABLE_FREE_SPACE, only_settled_doubts
from service.stages.search import RETRY_WARNING


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


def perspective_scan(camera: np.ndarray, fov_deg: float, pixels: int) -> np.ndarray:
    """``[P, 3]``: the surface ``z = height(x, y)`` (``|x|, |y| <= 1``) where the rays of a pinhole camera at
    ``camera [3]``, looking at the origin, first meet it (marched in steps, then interpolated)."""
    look = -camera / np.linalg.norm(camera)
    right = np.cross(look, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, look)
    half = np.tan(np.radians(fov_deg / 2))
    u, v = np.meshgrid(np.linspace(-half, half, pixels), np.linspace(-half, half, pixels))
    rays = look + u.reshape(-1, 1) * right + v.reshape(-1, 1) * up  # [R, 3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    along = camera + np.linspace(0.5, 4.0, 500)[None, :, None] * rays[:, None, :]  # [R, T, 3]
    above = along[..., 2] - height(along[..., 0], along[..., 1])  # [R, T] > 0: in front of the surface
    on_patch = (np.abs(along[..., 0]) <= 1) & (np.abs(along[..., 1]) <= 1)
    crossing = (above[:, :-1] > 0) & (above[:, 1:] <= 0) & on_patch[:, 1:]  # [R, T - 1]
    ray = np.flatnonzero(crossing.any(axis=1))
    step = crossing[ray].argmax(axis=1)
    a0, a1 = above[ray, step], above[ray, step + 1]
    share = (a0 / (a0 - a1))[:, None]
    return along[ray, step] + share * (along[ray, step + 1] - along[ray, step])


def test_a_wide_angle_perspective_scan_keeps_the_truth_out_of_free_space() -> None:
    """A pinhole camera close to the surface (80 deg field of view) breaks the parallel rays the depth map assumes;
    the right pose still leaves free space empty and a pose half a turn off does not."""
    source_to_target = turn(np.array([0.3, -1.0, 0.2]), 25.0)
    target = perspective_scan(np.array([0.0, 0.0, 1.5]), 80.0, 120)
    source = perspective_scan(source_to_target.T @ np.array([0.0, 0.0, 1.5]), 80.0, 120) @ source_to_target
    views = (range_view(source), range_view(target))
    assert views != (None, None)
    assert pose_free_space(*views, source, target, source_to_target, np.zeros(3)) < 0.02
    off = turn(np.array([1.0, 0.0, 0.0]), 180.0)  # about the target's centroid
    centre = target.mean(axis=0)
    assert pose_free_space(*views, source, target, off @ source_to_target, centre - off @ centre) > RELIABLE_FREE_SPACE


def test_a_stray_point_far_away_neither_widens_the_map_nor_overflows_its_cells() -> None:
    """One point 1e30 away (a sensor's glitch) leaves the depth map the size of the image's own, and points that far
    fall off it without an integer overflow (numpy warnings are errors here)."""
    scan = pixel_grid_scan(np.eye(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        view = range_view(np.vstack([scan, [[1e30, 0.0, 0.0]]]))
        assert view is not None and view.nearest.size <= 2 * range_view(scan).nearest.size
        assert free_space_share(view, np.array([[1e30, 1e30, 1e30], [-1e30, 0.0, 0.0]])) == 0.0


def test_loose_fits_and_poses_only_the_second_search_found_are_the_doubts_it_settles() -> None:
    def result(*warnings: str) -> SimpleNamespace:  # only_settled_doubts reads the warnings alone
        return SimpleNamespace(warnings=list(warnings))

    loose = "loose fit: of the source points within 3 inlier distances ..."
    assert only_settled_doubts(result(loose)) and only_settled_doubts(result(loose, RETRY_WARNING))
    assert only_settled_doubts(result(RETRY_WARNING))
    assert not only_settled_doubts(result())  # nothing to settle
    assert not only_settled_doubts(result(RETRY_WARNING, "poor fit: inlier ratio 0.31 < 0.45 ..."))
    assert not only_settled_doubts(result(loose, "ambiguous: a pose 180 deg away fits almost as well ..."))
