"""The refine stage on its own: ICP of the candidate poses, candidate ranking and multistart."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob
from stage_inputs import working_clouds

from service.icp import IcpResult, Surface
from service.multistart import multistart
from service.options import RegistrationOptions
from service.stages.normalise import SHORT_REFINE_STRIDE
from service.stages.ranking import rank_candidates
from service.stages.refine import CANDIDATE_ITERATIONS, refine, refine_pose, short_refine

R_TRUE = Rotation.from_euler("zyx", [6.0, -4.0, 3.0], degrees=True).as_matrix()
T_TRUE = np.array([0.05, -0.02, 0.03])


def working(**overrides):
    src = asymmetric_blob(800, 0)
    tgt = asymmetric_blob(800, 1) @ R_TRUE.T + T_TRUE  # an independent sampling of the same surface
    return working_clouds(src, tgt, {"working_size": 256, **overrides}, reference_radius=1.0, keypoints=64)


def angle_deg(R_a, R_b) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R_a.T @ R_b) - 1) / 2, -1, 1))))


def test_without_a_refinement_a_single_start_is_returned_unchanged() -> None:
    work, options = working()
    refined = refine(work, [(R_TRUE, T_TRUE)], options)
    assert refined.rotation is R_TRUE and refined.translation is T_TRUE
    assert (refined.pick, refined.warnings, refined.ambiguity, refined.surface) == (0, (), None, None)


@pytest.mark.parametrize("truth_at", [0, 1])
def test_without_a_refinement_the_better_fitting_of_two_starts_is_returned_as_it_is(truth_at) -> None:
    """The caller's guess beside the network's pose: whichever fits better, unrefined."""
    work, options = working()
    wrong = (Rotation.from_euler("x", 40, degrees=True).as_matrix() @ R_TRUE, T_TRUE)
    starts = [wrong, (R_TRUE, T_TRUE)] if truth_at == 1 else [(R_TRUE, T_TRUE), wrong]
    refined = refine(work, starts, options)
    assert refined.pick == truth_at and (refined.warnings, refined.ambiguity, refined.surface) == ((), None, None)
    np.testing.assert_array_equal(refined.rotation, R_TRUE)
    np.testing.assert_array_equal(refined.translation, T_TRUE)


@pytest.mark.parametrize(("mode", "within"), [("icp", 5.0), ("icp-plane", 0.5), ("icp-plane-multistart", 0.5)])
def test_each_mode_refines_the_identity_start_towards_the_truth(mode, within) -> None:
    work, options = working(refine=mode)
    refined = refine(work, [(np.eye(3), np.zeros(3))], options)
    # from 7.7 deg off; measured 3.3 (point-to-point between independent samplings) and 0.08 deg
    assert angle_deg(refined.rotation, R_TRUE) < within
    assert (refined.surface is None) == (mode == "icp")


def test_refine_pose_honours_the_iteration_cap() -> None:
    work, _ = working()
    one = refine_pose(work, np.eye(3), np.zeros(3), "icp", 0.2, 1, None)
    assert isinstance(one, IcpResult) and one.iterations <= 1


def test_ranking_picks_the_start_in_the_right_basin_wherever_it_is() -> None:
    work, _ = working(refine="icp-plane")
    surface = Surface.of(work.tgt_r)
    short = partial(short_refine, work, refine="icp-plane", distance=0.1 * work.norm.scale, surface=surface)
    wrong = (Rotation.from_euler("x", 120, degrees=True).as_matrix(), np.zeros(3))
    ranked = rank_candidates(work, [wrong, (np.eye(3), np.zeros(3))], short)
    assert ranked.pick == 1 and angle_deg(ranked.rotation, R_TRUE) < 5.0 and ranked.ambiguity is None
    refined = refine(work, [wrong, (np.eye(3), np.zeros(3))], RegistrationOptions(refine="icp-plane"))
    assert refined.pick == 1 and angle_deg(refined.rotation, R_TRUE) < 0.5


def test_multistart_keeps_a_refined_pose_that_fits_best() -> None:
    work, _ = working()
    refined = refine_pose(work, R_TRUE, T_TRUE, "icp-plane", 0.1 * work.norm.scale, 30, None)
    kept = multistart(work.src_r, work.tgt_r, refined, work.norm.scale, 0.1 * work.norm.scale, 30)
    assert kept is refined


def test_multistart_recovers_a_pose_turned_into_a_wrong_basin() -> None:
    work, _ = working()
    turn = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    start = IcpResult(turn @ R_TRUE, T_TRUE, 0, 0.0, 0.0)  # as if a refinement had stopped 30 degrees off
    moved = multistart(work.src_r, work.tgt_r, start, work.norm.scale, 0.1 * work.norm.scale, 30)
    assert angle_deg(moved.rotation, R_TRUE) < angle_deg(start.rotation, R_TRUE) - 20


def test_short_refinements_move_every_third_source_point_with_the_full_clouds_normals() -> None:
    work, _ = working(refine="icp-plane")
    points, surface = work.short_points, work.short_surface
    np.testing.assert_array_equal(points, work.src_r[::SHORT_REFINE_STRIDE])
    np.testing.assert_array_equal(surface.normals, work.source_surface.normals[::SHORT_REFINE_STRIDE])
    assert work.short_surface is surface and work.source_surface is work.source_surface  # built once
    start = Rotation.from_euler("x", 10.0, degrees=True).as_matrix() @ R_TRUE
    (rotation,), (translation,) = short_refine(work, [(start, T_TRUE)], "icp-plane", 0.1 * work.norm.scale,
                                               work.target_surface)
    alone = refine_pose(work, start, T_TRUE, "icp-plane", 0.1 * work.norm.scale, CANDIDATE_ITERATIONS,
                        work.target_surface, short=True)  # the same stages, one start at a time
    assert alone.iterations <= 2 * CANDIDATE_ITERATIONS
    np.testing.assert_allclose(rotation, alone.rotation, atol=1e-9)
    np.testing.assert_allclose(translation, alone.translation, atol=1e-9)
    assert angle_deg(rotation, R_TRUE) < angle_deg(start, R_TRUE) - 3.0  # the basin is found from 10 deg
