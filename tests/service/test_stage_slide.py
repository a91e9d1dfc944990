"""The slide check on its own: a right pose stays; a pose slid along the walls of a room comes back."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from real_scan_cases import GENERAL, assert_registers
from scipy.spatial.transform import Rotation
from shapes import room_scene
from stage_inputs import working_clouds

from bench.real_scans import data_dir
from service.icp import IcpResult
from service.registrar import Registrar
from service.rotation_search import rank_hypotheses
from service.stages.normalise import normalise
from service.stages.pipeline import Stages
from service.stages.ranking import (
    close_fit,
    rank_candidates,
    samples_the_surface,
    shift_ambiguity,
    with_translations,
)
from service.stages.refine import refine
from service.stages.sample import sample
from service.stages.slide import closer_of, fits_poorly, slide
from service.stages.validate import validate

R_TRUE = Rotation.from_euler("zyx", [20.0, 0.0, 0.0], degrees=True).as_matrix()
T_TRUE = np.array([0.6, -0.3, 0.1])


def room_pair():
    """Two overlapping partial views of one furnished room (metres), the target moved by ``R_TRUE, T_TRUE``."""
    rng = np.random.default_rng(3)
    scene = room_scene(rng, 2000, boxes=30)  # a furnished room: the boxes tell places apart
    source = scene[scene[:, 0] < 3.0]
    target = scene[scene[:, 0] > 1.0] @ R_TRUE.T + T_TRUE
    return source, target


def working():
    source, target = room_pair()
    return working_clouds(source, target, reference_radius=1.0)


def test_a_right_pose_fits_and_is_returned_unchanged():
    work, options = working()
    refined = refine(work, [(R_TRUE, T_TRUE)], options)
    assert not fits_poorly(work, refined.rotation, refined.translation)
    assert slide(work, refined, options) is refined


def test_a_slid_room_fragment_comes_back():
    """3DMatch kitchen fragments: the plain registration gets the rotation and slides 0.87 m along the walls."""
    path = data_dir() / "3dm_geot_kitchen_6_0.npz"
    if not path.exists():
        pytest.skip(f"real-scan set absent ({path.parent}; set MFGNET_REAL_DATA)")
    with np.load(path) as data:
        source, target, truth = data["source"], data["target"], data["transform"]
    with_slide = Registrar(GENERAL)
    without = Registrar(GENERAL, stages=dataclasses.replace(Stages(), slide=lambda work, refined, options: refined))
    errors, results = {}, {}
    for name, registrar in (("with", with_slide), ("without", without)):
        results[name] = registrar.register(source, target, refine="icp-plane", rotation_search=False)
        errors[name] = np.linalg.norm(results[name].translation - truth[:3, 3])
    assert errors["without"] > 0.5 and errors["with"] < 0.3, errors  # 3DMatch success: under 0.3 m
    # by inlier ratio on the working clouds the place 0.82 m along the walls fitted almost as well (0.50 vs 0.53); by
    # close fit to the target it does not, and the right result is reliable
    assert results["with"].reliable, results["with"].warnings


def test_without_a_refinement_nothing_is_tried():
    work, _ = working()
    source, target = room_pair()
    options = validate(source, target, None, {"refine": "none"}, 3, 128).options
    refined = refine(work, [(np.eye(3), np.zeros(3))], options)
    assert slide(work, refined, options) is refined


def test_each_search_candidate_is_also_tried_at_its_best_translations():
    work, _ = working()
    starts = [(R_TRUE, T_TRUE), (np.eye(3), np.zeros(3))]
    poses, origin = with_translations(work, starts, count=2)
    assert poses[:2] == starts and origin[:2] == [0, 1]
    assert len(poses) == len(origin) <= 2 + 2 * 2
    for (R, _), index in zip(poses[2:], origin[2:], strict=True):
        assert R is starts[index][0]  # the candidate's own rotation, at another translation


def test_a_second_place_that_fits_almost_as_well_makes_the_result_ambiguous():
    work, _ = working()
    far, near = np.array([0.5, 0.0, 0.0]), np.array([0.01, 0.0, 0.0])  # metres; the room is ~4 m across
    rotations = np.stack([R_TRUE] * 3)  # [3, 3, 3]
    translations = np.stack([T_TRUE, T_TRUE + near, T_TRUE + far])  # [3, 3]
    warning = shift_ambiguity(work, rotations, translations, np.array([0.50, 0.50, 0.48]), best=0)
    assert warning is not None and warning.startswith("ambiguous: a pose that moves the source 0.5 further")
    assert shift_ambiguity(work, rotations, translations, np.array([0.50, 0.50, 0.40]), best=0) is None  # fits worse
    assert shift_ambiguity(work, rotations[:2], translations[:2], np.array([0.50, 0.50]), best=0) is None  # same place


def as_poses(starts):
    """A short refinement that leaves every start where it is: ``R [C, 3, 3]``, ``t [C, 3]``."""
    return np.stack([R for R, _ in starts]), np.stack([t for _, t in starts])


def test_the_close_fit_tells_the_right_place_from_one_slid_a_few_centimetres():
    work, _ = working()
    shifts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.2, 0.0, 0.0]])  # metres along a wall
    fits = close_fit(work, np.stack([R_TRUE] * 3), T_TRUE + shifts)
    assert fits[0] > 1.5 * fits[1] and fits[1] >= fits[2], fits


def test_candidates_are_ranked_by_their_close_fit():
    work, _ = working()
    slid = (R_TRUE, T_TRUE + np.array([0.05, 0.0, 0.0]))
    assert rank_candidates(work, [slid, (R_TRUE, T_TRUE)], as_poses).pick == 1


def test_close_fits_only_rank_where_the_target_is_denser_than_its_working_cloud():
    """On a target no denser than its working cloud a close fit would only tighten the inlier test on the same sparse
    samples: the ranking keeps the inlier ratio there (sparse ModelNet40 pairs at any orientation lost 7 of 100)."""
    work, _ = working()
    assert samples_the_surface(work)  # ~19,000 target points for 768 working ones
    source, target = room_pair()
    sparse = np.random.default_rng(0).choice(len(target), 1500, replace=False)
    request = validate(source, target[sparse], None, {"refine": "icp-plane"}, 3, 128)
    thin = normalise(sample(request), 1.0)
    assert not samples_the_surface(thin)
    slid = (R_TRUE, T_TRUE + np.array([0.05, 0.0, 0.0]))
    ranked = rank_candidates(thin, [slid, (R_TRUE, T_TRUE)], as_poses)
    ratios = rank_hypotheses(
        thin.working_source, thin.tgt_w, *as_poses([slid, (R_TRUE, T_TRUE)]), thin.inlier_distance
    )[1]
    assert ranked.pick == int(np.argmax(ratios))  # by inlier ratio (ties: the first)
    full = IcpResult(*slid, iterations=30, inlier_ratio=0.5, residual_rms=0.01)
    assert closer_of(thin, full, R_TRUE, T_TRUE)[1] is slid[1]  # the refinement is kept


def test_a_refinement_that_slides_off_the_surface_gives_way_to_its_start():
    work, _ = working()
    slid = T_TRUE + np.array([0.05, 0.0, 0.0])
    moved_off = IcpResult(R_TRUE, slid, iterations=30, inlier_ratio=0.5, residual_rms=0.01, warnings=("w",))
    assert closer_of(work, moved_off, R_TRUE, T_TRUE)[1] is T_TRUE
    assert closer_of(work, moved_off, R_TRUE, T_TRUE)[2] == ()
    stayed = IcpResult(R_TRUE, T_TRUE, iterations=5, inlier_ratio=0.5, residual_rms=0.01, warnings=("w",))
    assert closer_of(work, stayed, R_TRUE, slid) == (R_TRUE, T_TRUE, ("w",))


def test_a_turned_room_fragment_in_millimetres_keeps_its_place():
    """A turned 3DMatch kitchen (this pair's third seeded turn when loaded alone): ranked by inlier ratio on the
    working clouds, the slid places won and the result came back 0.9 m off."""
    assert_registers("3dm_geot_kitchen_6_0", 0, "turned-3", 1000.0)
