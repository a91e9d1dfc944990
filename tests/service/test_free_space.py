"""A range image's viewing axis and free space (service.free_space), on synthetic scans of a bumpy surface; which doubts
the free-space stage settles, and on what evidence."""

from __future__ import annotations

import dataclasses
import warnings
from types import SimpleNamespace

import numpy as np
from stage_inputs import result_at, working_clouds

from service.free_space import (
    COARSE_VIEW_NEIGHBOURS,
    RANGE_IMAGE_CORRELATION,
    pose_free_space,
    range_view,
    view_shares,
)
from service.quality import LOOSE_FIT, WORKING_LOOSE_FIT
from service.result import RegistrationResult
from service.stages.consensus import loose_between_range_images
from service.stages.free_space import (
    COARSE_CONFIRMS_BELOW,
    CONFIRMED_BY_FREE_SPACE,
    CONFIRMS_BELOW,
    CONFIRMS_SEEING,
    RELIABLE_FREE_SPACE,
    free_space,
    free_space_of,
    only_settled_doubts,
)
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


def test_a_range_image_with_noise_of_a_pixel_spacing_gives_its_viewing_axis_over_more_neighbours() -> None:
    """Gaussian noise of one pixel spacing turns the normals and densities of 10 neighbours to noise; read over
    ``COARSE_VIEW_NEIGHBOURS`` the image still explains its density (decisions/0094)."""
    rotation = turn(np.array([1.0, 2.0, 0.5]), 40.0)
    noisy = pixel_grid_scan(rotation) + np.random.default_rng(0).normal(scale=2 / 159, size=(160 * 160, 3))
    assert range_view(noisy) is None
    view = range_view(noisy, neighbours=COARSE_VIEW_NEIGHBOURS)
    assert view is not None and view.correlation >= RANGE_IMAGE_CORRELATION
    assert abs(view.axis @ rotation[:, 2]) > np.cos(np.radians(5.0))


def test_a_random_half_of_a_range_image_maps_what_it_saw() -> None:
    """A random half of the pixels leaves near pairs among gaps: cells sized by the nearest neighbour would often be
    empty, and the edges of those holes would leave little seen; sized by the mean spacing, most of the points lie
    in seen cells."""
    rotation = turn(np.array([1.0, 2.0, 0.5]), 40.0)
    full = pixel_grid_scan(rotation, pixels=400)
    thinned = full[np.random.default_rng(0).random(len(full)) < 0.5]
    view = range_view(thinned)
    assert view is not None and abs(view.axis @ rotation[:, 2]) > np.cos(np.radians(5.0))
    assert view_shares(view, thinned)[1] > 0.8


def even_sample() -> np.ndarray:
    """``[N > 4000, 3]``: the bumpy surface with its points spread evenly over it (as a mesh sampler or a fused
    fragment's voxels give them), each pixel of a 400 x 400 grid kept against its cosine."""
    dense = pixel_grid_scan(np.eye(3), pixels=400)
    gy, gx = np.gradient(dense[:, 2].reshape(400, 400), 2 / 399)
    cos = 1 / np.sqrt(1 + gx.ravel() ** 2 + gy.ravel() ** 2)  # [N] of the surface normal and the z axis
    return dense[np.random.default_rng(0).random(len(dense)) < cos.min() / cos]


def test_uniform_samples_of_the_surface_are_no_range_image() -> None:
    """Points spread evenly over the surface have a density that no viewing direction explains."""
    uniform = even_sample()
    assert len(uniform) > 4000
    assert range_view(uniform) is None


def test_the_truth_leaves_free_space_empty_and_a_half_turn_does_not() -> None:
    target = pixel_grid_scan(np.eye(3))
    source_to_target = turn(np.array([0.3, -1.0, 0.2]), 25.0)  # the source scan: the surface turned away from z
    source = pixel_grid_scan(np.eye(3), pixels=150) @ source_to_target  # the same surface in the source's frame
    views = (range_view(source), range_view(target))
    assert views[0] is not None and views[1] is not None
    R, t = source_to_target, np.zeros(3)
    assert pose_free_space(*views, source, target, R, t).share < 0.01
    half = turn(np.array([1.0, 0.0, 0.0]), 180.0)  # the right pose turned half a turn about the target's x axis
    share = pose_free_space(*views, source, target, half @ R, half @ t).share
    assert share > RELIABLE_FREE_SPACE, share


def test_points_hidden_behind_what_the_sensor_saw_are_no_evidence() -> None:
    target = pixel_grid_scan(np.eye(3))
    view = range_view(target)
    assert view is not None
    behind = target[::7] - 0.5 * view.axis  # the same surface moved along the axis: behind it from one side
    assert view_shares(view, behind)[0] == 0.0
    beside = target[::7] + np.array([5.0, 0.0, 0.0])  # cells the sensor never saw
    assert view_shares(view, beside) == (0.0, 0.0)


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
    assert pose_free_space(*views, source, target, source_to_target, np.zeros(3)).share < 0.02
    off = turn(np.array([1.0, 0.0, 0.0]), 180.0)  # about the target's centroid
    centre = target.mean(axis=0)
    wrong = pose_free_space(*views, source, target, off @ source_to_target, centre - off @ centre)
    assert wrong is not None and wrong.share > RELIABLE_FREE_SPACE


def test_a_stray_point_far_away_neither_widens_the_map_nor_overflows_its_cells() -> None:
    """One point 1e30 away (a sensor's glitch) leaves the depth map the size of the image's own, and points that far
    fall off it without an integer overflow (numpy warnings are errors here)."""
    scan = pixel_grid_scan(np.eye(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        view = range_view(np.vstack([scan, [[1e30, 0.0, 0.0]]]))
        assert view is not None and view.nearest.size <= 2 * range_view(scan).nearest.size
        assert view_shares(view, np.array([[1e30, 1e30, 1e30], [-1e30, 0.0, 0.0]])) == (0.0, 0.0)


def test_loose_fits_and_poses_only_the_second_search_found_are_the_doubts_it_settles() -> None:
    def result(*warnings: str) -> SimpleNamespace:  # only_settled_doubts reads the warnings alone
        return SimpleNamespace(warnings=list(warnings))

    loose = "loose fit: of the source points within 3 inlier distances ..."
    assert only_settled_doubts(result(loose)) and only_settled_doubts(result(loose, RETRY_WARNING))
    assert only_settled_doubts(result(RETRY_WARNING))
    assert not only_settled_doubts(result())  # nothing to settle
    assert not only_settled_doubts(result(RETRY_WARNING, "poor fit: inlier ratio 0.31 < 0.45 ..."))
    assert not only_settled_doubts(result(loose, "ambiguous: a pose 180 deg away fits almost as well ..."))


def loose_result(R: np.ndarray, t: np.ndarray) -> RegistrationResult:
    """A result at ``(R, t)`` that only a loose fit keeps from ``reliable`` (a doubt free space settles)."""
    return result_at(R, t, reliable=False, inlier_ratio=0.6, warnings=[f"{LOOSE_FIT}: ..."], iterations=4)


SOURCE_TO_TARGET = turn(np.array([0.3, -1.0, 0.2]), 25.0)


def scan_pair(noisy_source: bool, noisy_target: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(source, target)`` float32: pixel-grid scans of the bumpy surface (150 and 160 pixels a side), the source
    moved by ``SOURCE_TO_TARGET.T``; each as asked with Gaussian noise of one pixel spacing (the target's drawn
    first)."""
    rng = np.random.default_rng(1)
    target = pixel_grid_scan(np.eye(3))
    if noisy_target:
        target = target + rng.normal(scale=2 / 159, size=target.shape)
    source = pixel_grid_scan(np.eye(3), pixels=150)
    if noisy_source:
        source = source + rng.normal(scale=2 / 149, size=source.shape)
    return (source @ SOURCE_TO_TARGET).astype(np.float32), target.astype(np.float32)


def test_free_space_confirms_a_pose_only_where_the_sensor_saw_the_other_scan() -> None:
    """The truth is confirmed; a pose that moves the other scan beside the image, where its sensor saw nothing, puts
    nothing in its free space either, and that is no evidence: it stays unconfirmed."""
    work, options = working_clouds(*scan_pair(noisy_source=False, noisy_target=False))
    assert work.range_views != (None, None)
    right = free_space(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), options, {})
    assert right.reliable and any(w.startswith(CONFIRMED_BY_FREE_SPACE) for w in right.warnings), right.warnings
    beside = free_space(work, loose_result(SOURCE_TO_TARGET, np.array([3.0, 0.0, 0.0])), options, {})
    assert not beside.reliable and not any(w.startswith(CONFIRMED_BY_FREE_SPACE) for w in beside.warnings)


def test_noisy_range_images_are_confirmed_by_their_coarser_views_at_the_tighter_bound() -> None:
    """Over 10 neighbours neither noisy scan is a range image; a confirmation reads both over
    ``COARSE_VIEW_NEIGHBOURS`` and then holds the share to ``COARSE_CONFIRMS_BELOW``."""
    work, options = working_clouds(*scan_pair(noisy_source=True, noisy_target=True))
    assert work.range_views == (None, None)
    assert all(view is not None and view.neighbours == COARSE_VIEW_NEIGHBOURS for view in work.confirming_views)
    right = free_space(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), options, {})
    assert right.reliable, right.warnings
    assert any(w.startswith(CONFIRMED_BY_FREE_SPACE) and f"<= {COARSE_CONFIRMS_BELOW}" in w for w in right.warnings)
    off = turn(np.array([1.0, 0.0, 0.0]), 4.0) @ SOURCE_TO_TARGET  # a few degrees off: a little in front of the scan
    shares = free_space_of(work, loose_result(off, np.zeros(3)), work.confirming_views)
    assert shares is not None and COARSE_CONFIRMS_BELOW < shares.share <= CONFIRMS_BELOW  # the 0.03 bound would pass it
    assert not free_space(work, loose_result(off, np.zeros(3)), options, {}).reliable


def test_a_coarser_view_beside_a_view_over_ten_neighbours_takes_part_at_the_tighter_bound() -> None:
    """A clean target (a range image over 10 neighbours) and a noisy source (one over 40 only): a confirmation reads
    both, so the tighter bound holds; a pose 3 deg off, which the 0.03 bound would pass, stays unconfirmed."""
    work, options = working_clouds(*scan_pair(noisy_source=True, noisy_target=False))
    views = work.confirming_views
    assert [view.neighbours for view in views] == [COARSE_VIEW_NEIGHBOURS, 10], views
    right = free_space(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), options, {})
    assert any(w.startswith(CONFIRMED_BY_FREE_SPACE) and f"<= {COARSE_CONFIRMS_BELOW}" in w for w in right.warnings)
    off = turn(np.array([1.0, 0.0, 0.0]), 3.0) @ SOURCE_TO_TARGET
    shares = free_space_of(work, loose_result(off, np.zeros(3)), views)
    assert shares is not None and COARSE_CONFIRMS_BELOW < shares.share <= CONFIRMS_BELOW
    assert not free_space(work, loose_result(off, np.zeros(3)), options, {}).reliable


def test_a_reliable_result_is_judged_on_the_views_over_ten_neighbours_alone() -> None:
    """The veto never reads the coarser views (they cost about twice the first reading): a ``reliable`` result over
    two noisy scans is passed through without them."""
    work, options = working_clouds(*scan_pair(noisy_source=True, noisy_target=True))
    result = dataclasses.replace(loose_result(SOURCE_TO_TARGET, np.zeros(3)), reliable=True, warnings=[])
    assert free_space(work, result, options, {}) is result
    assert "confirming_views" not in vars(work)


def test_a_coarser_view_beside_a_cloud_with_no_view_confirms_nothing() -> None:
    """A fused fragment cut by a plane can pass the coarser reading alone; a coarser view counts only where the other
    cloud has a view too, so beside an even sample of the surface (no range image at any reading) none is kept."""
    source, _ = scan_pair(noisy_source=True, noisy_target=True)  # the noisy source, as in the tests above
    even = even_sample()
    work, options = working_clouds(source, even.astype(np.float32))
    assert range_view(even, neighbours=COARSE_VIEW_NEIGHBOURS) is None
    assert range_view(source, neighbours=COARSE_VIEW_NEIGHBOURS) is not None
    assert work.confirming_views == (None, None)
    assert not free_space(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), options, {}).reliable


def test_a_confirmation_needs_both_clouds_to_be_range_images() -> None:
    """Beside a cloud with no view, one range image's free space is no evidence: a pose half a turn off about an axis
    across its view puts the other scan's surface behind what its sensor saw, where nothing is known (a scanned toilet
    so turned left 0.014 of its points in the target's free space, below the 0.03 bound; decisions/0096). So a
    range image beside an even sample of the surface confirms not even the truth, and the descriptors, not free
    space, settle its loose fit."""
    source, _ = scan_pair(noisy_source=False, noisy_target=False)
    work, options = working_clouds(source, even_sample().astype(np.float32))
    views = work.confirming_views
    assert views[0] is not None and views[1] is None
    shares = free_space_of(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), views)
    assert shares is not None and shares.share <= CONFIRMS_BELOW and shares.seen >= CONFIRMS_SEEING  # as a lone view
    assert not free_space(work, loose_result(SOURCE_TO_TARGET, np.zeros(3)), options, {}).reliable
    loose = dataclasses.replace(loose_result(SOURCE_TO_TARGET, np.zeros(3)), warnings=[f"{WORKING_LOOSE_FIT} ..."])
    assert not loose_between_range_images(work, loose)


def test_a_cloud_of_stacked_duplicate_points_gives_no_view() -> None:
    """Where most points have a duplicate, the median nearest-neighbour distance is 0: the density is no sensor's, and
    the mean spacing does not make it a view."""
    scan = pixel_grid_scan(np.eye(3))
    assert range_view(np.vstack([scan, scan])) is None


def test_the_descriptors_leave_a_noisy_range_images_loose_fit_to_free_space() -> None:
    """Free space judges a loose fit between noisy range images on their coarser views, so the consensus stage does
    not settle it in its place (decisions/0093, 0094)."""
    work, _ = working_clouds(*scan_pair(noisy_source=True, noisy_target=True))
    result = dataclasses.replace(loose_result(SOURCE_TO_TARGET, np.zeros(3)), warnings=[f"{WORKING_LOOSE_FIT} ..."])
    assert work.range_views == (None, None)
    assert loose_between_range_images(work, result)
