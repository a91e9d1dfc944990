"""The flip check on its own: a searched pose turned half a turn about one of the source's axes comes back, also when
it lies far from the right place; a pose that fits, or one on a target no denser than its working cloud, is left
alone."""

from __future__ import annotations

import dataclasses

import numpy as np
from real_scan_cases import assert_registers
from scipy.spatial.transform import Rotation
from shapes import range_patch
from stage_inputs import working_clouds

from service.stages.flip import flip
from service.stages.partial import half_turns
from service.stages.refine import Refined, refine
from service.stages.slide import fits_poorly

R_TRUE = Rotation.from_euler("zyx", [40.0, -20.0, 10.0], degrees=True).as_matrix()
T_TRUE = np.array([0.3, -0.2, 0.5])


def working(target_points: int):
    """Part of the patch as the source, the whole patch moved by ``R_TRUE, T_TRUE`` as the target."""
    patch = range_patch(target_points)
    return working_clouds(patch[patch[:, 0] < 0.7], patch @ R_TRUE.T + T_TRUE)


def angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(R_a.T @ R_b).magnitude()))


def half_turned(work) -> list[Refined]:
    """The right pose turned half a turn about each principal axis of the moved working source."""
    R_h, t_h = half_turns(work.working_source, R_TRUE, T_TRUE)
    return [Refined(R, t, 0, (), None, work.target_surface) for R, t in zip(R_h, t_h, strict=True)]


def test_a_pose_that_fits_is_left_alone():
    work, options = working(8000)
    refined = refine(work, [(R_TRUE, T_TRUE)], options)
    assert flip(work, refined, options) is refined


def test_half_turned_poses_that_fit_poorly_come_back_on_a_dense_target():
    work, options = working(8000)  # 8,000 target points: over 4x the working cloud's
    came_back = 0
    for start in half_turned(work):
        back = flip(work, start, options)
        if fits_poorly(work, start.rotation, start.translation):
            assert angle(back.rotation, R_TRUE) < 1 and np.linalg.norm(back.translation - T_TRUE) < 0.01
            came_back += 1
        else:  # the patch turned about its normal overlays itself well enough: not a poor fit, not tried
            assert back is start
    assert came_back == 2


def test_half_turned_poses_far_from_the_right_place_come_back():
    """Each half turn also slid half the patch's length along it: turning it back about the moved source's own centroid
    leaves it there, so its rotation must be tried at its best translations too. The search's ambiguity, about the
    pose that the flip replaces, goes with it."""
    work, options = working(8000)
    for start in half_turned(work):
        slid = dataclasses.replace(start, translation=start.translation + np.array([0.5, 0.0, 0.0]),
                                   ambiguity="ambiguous: the search's close second")
        assert fits_poorly(work, slid.rotation, slid.translation)
        back = flip(work, slid, options)
        assert angle(back.rotation, R_TRUE) < 1 and np.linalg.norm(back.translation - T_TRUE) < 0.01
        assert back.ambiguity is None


def test_with_a_target_no_denser_than_its_working_cloud_nothing_is_tried():
    work, options = working(768)
    for start in half_turned(work):
        assert flip(work, start, options) is start


def test_a_turned_dragon_that_came_back_half_a_turn_off_registers():
    """``dragon_168_120``'s second seeded turn: the search's result was 176 deg off."""
    assert_registers("dragon_168_120", 0, "turned-2")

