"""The slide check on its own: a right pose stays; a pose slid along the walls of a room comes back."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import room_scene

from service.registrar import Registrar
from service.stages.normalise import normalise
from service.stages.pipeline import Stages
from service.stages.ranking import shift_ambiguity, with_translations
from service.stages.refine import refine
from service.stages.sample import sample
from service.stages.slide import fits_poorly, slide
from service.stages.validate import validate

GENERAL = Path(__file__).resolve().parents[2] / "service" / "models" / "general"
R_TRUE = Rotation.from_euler("zyx", [20.0, 0.0, 0.0], degrees=True).as_matrix()
T_TRUE = np.array([0.6, -0.3, 0.1])


def real_data_dir() -> Path:
    return Path(os.environ.get("MFGNET_REAL_DATA") or Path(__file__).resolve().parents[3] / "shared" / "data" / "real")


def room_pair():
    """Two overlapping partial views of one furnished room (metres), the target moved by ``R_TRUE, T_TRUE``."""
    rng = np.random.default_rng(3)
    scene = room_scene(rng, 2000, boxes=30)  # a furnished room: the boxes tell places apart
    source = scene[scene[:, 0] < 3.0]
    target = scene[scene[:, 0] > 1.0] @ R_TRUE.T + T_TRUE
    return source, target


def working():
    source, target = room_pair()
    request = validate(source, target, None, {"refine": "icp-plane"}, 3, 128)
    return normalise(sample(request), 1.0), request.options


def test_a_right_pose_fits_and_is_returned_unchanged():
    work, options = working()
    refined = refine(work, [(R_TRUE, T_TRUE)], options)
    assert not fits_poorly(work, refined.rotation, refined.translation)
    assert slide(work, refined, options) is refined


def test_a_slid_room_fragment_comes_back():
    """3DMatch kitchen fragments: the plain registration gets the rotation and slides 0.87 m along the walls."""
    path = real_data_dir() / "3dm_geot_kitchen_6_0.npz"
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
    # the place 0.85 m along the walls fits almost as well (inlier ratio 0.50 vs 0.53): right, but not reliable
    assert not results["with"].reliable
    assert any(w.startswith("ambiguous: a pose that moves the source") for w in results["with"].warnings)


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
