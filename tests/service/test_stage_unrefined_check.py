"""The unrefined check (``service/stages/unrefined_check.py``): with ``refine: "none"``, a ``reliable`` pose is one a
short refinement leaves within ``MOVE_DEG`` and ``SHIFT`` inlier distances; alone on the working clouds, and through
the in-process API on the README's surface."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
from pair_checks import needs_dense
from real_scan_cases import skip_without_general
from stage_inputs import result_at, working_clouds

from service.manifest import bundled_models_dir
from service.quality import POOR_FIT
from service.registrar import Registrar
from service.rotation_search import rotation_between_deg
from service.stages.pipeline import Stages
from service.stages.unrefined_check import MOVE_DEG, SHIFT, unrefined_check


def surface(turn_deg: float = 30.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The README's closed surface (2,000 points) and its target turned ``turn_deg`` about z and moved 0.1 along x:
    ``source [N, 3], target [N, 3], R [3, 3], t [3]``."""
    d = np.random.default_rng(0).normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    source = d * (1 + 0.3 * d[:, :1] ** 3 + 0.2 * np.sin(3 * d[:, 1:2])) * [1.0, 0.8, 0.6]  # [N, 3]
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    R, t = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.array([0.1, 0.0, 0.0])
    return source, source @ R.T + t, R, t


def about_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.fixture(scope="module")
def unrefined():
    source, target, R, t = surface()
    work, options = working_clouds(source, target, {"refine": "none"})
    return work, options, R, t


def test_the_true_pose_is_left_reliable(unrefined) -> None:
    work, options, R, t = unrefined
    result = result_at(R, t)
    assert unrefined_check(work, result, options, {}) is result


@pytest.mark.parametrize("off_deg", [8.0, 20.0])
def test_a_pose_degrees_off_is_withdrawn_naming_how_far_a_refinement_moves_it(unrefined, off_deg) -> None:
    work, options, R, t = unrefined
    checked = unrefined_check(work, result_at(about_z(off_deg) @ R, t), options, timing := {})
    assert not checked.reliable and checked.warnings[-1].startswith(f"{POOR_FIT}: a short refinement turns the "
                                                                    "unrefined pose")
    moved = float(checked.warnings[-1].split("pose ")[1].split(" deg")[0])
    assert moved > MOVE_DEG and timing["postprocess"] > 0
    assert rotation_between_deg(checked.rotation, R) == pytest.approx(off_deg)  # the pose is kept


def test_a_pose_slid_more_than_an_inlier_distance_is_withdrawn(unrefined) -> None:
    work, options, R, t = unrefined
    slid = t + np.array([0.0, 0.0, 3 * SHIFT * work.inlier_distance])  # along the surface's shortest axis
    checked = unrefined_check(work, result_at(R, slid), options, {})
    assert not checked.reliable and "inlier distances" in checked.warnings[-1]


def test_refined_and_unreliable_results_are_not_checked(unrefined) -> None:
    work, _, R, t = unrefined
    _, refined_options = working_clouds(*surface()[:2])  # refine: icp-plane
    wrong = result_at(about_z(20.0) @ R, t)
    assert unrefined_check(work, wrong, refined_options, {}) is wrong
    _, options, _, _ = unrefined
    unreliable = result_at(about_z(20.0) @ R, t, reliable=False)
    assert unrefined_check(work, unreliable, options, {}) is unreliable


def test_the_readmes_unrefined_request_is_not_reliable_where_it_is_20_deg_off() -> None:
    """The README's pair with ``refine="none"`` came back 20.5 deg off, ``reliable``, with no warning."""
    from service.in_process import LocalRegistrar

    skip_without_general()
    source, target, R, _ = surface()
    result = LocalRegistrar("general", threads=1).register(source, target, refine="none")
    assert rotation_between_deg(result.rotation, R) > MOVE_DEG  # the network's pose, as it is
    assert not result.reliable and any(w.startswith(f"{POOR_FIT}: a short refinement") for w in result.warnings)


@needs_dense
def test_on_small_working_clouds_right_results_stay_reliable() -> None:
    """Every working point is moved where the short points are fewer than ``CHECK_POINTS``, and a shift is measured
    against the working target's spacing where it is wider than the inlier distance: at ``working_size`` 128, 43
    short points turned right poses up to 27 deg, and right poses moved 1-2 inlier distances of a sparser cloud (11
    right results of the first 40 dense pairs lost ``reliable``)."""
    from model.data import make_test_pairs

    skip_without_general()
    pairs = make_test_pairs("dense", "test", 12, 0)
    general = Registrar(bundled_models_dir() / "general", threads=1, warmup=False)
    unchecked = Registrar(bundled_models_dir() / "general", threads=1, warmup=False,
                          stages=dataclasses.replace(Stages(), unrefined_check=lambda work, result, options, t: result))
    for i in range(12):
        src, tgt = pairs["source"][i], pairs["target"][i]
        options = {"refine": "none", "working_size": 128, "keypoints": 64}
        plain, checked = unchecked.register(src, tgt, **options), general.register(src, tgt, **options)
        right = (rotation_between_deg(plain.rotation, pairs["rotation"][i]) < 5
                 and np.linalg.norm(plain.translation - pairs["translation"][i]) < 0.05)
        assert checked.reliable or not (plain.reliable and right), (i, checked.warnings)


def test_the_warning_counts_inlier_distances_and_names_the_bound_applied() -> None:
    """On a sparse working cloud the bound is the target's spacing, wider than an inlier distance: the warning gave
    the shift in spacings and called them inlier distances, against a bound of 1."""
    source, target, R, t = surface()
    work, options = working_clouds(source, target, {"refine": "none", "working_size": 64, "keypoints": 32})
    spacing = float(np.median(work.target_spacings)) / work.inlier_distance  # in inlier distances
    assert spacing > 1.5
    slid = t + np.array([0.0, 0.0, 2 * spacing * work.inlier_distance])
    warning = unrefined_check(work, result_at(R, slid), options, {}).warnings[-1]
    found = re.search(r"moves it ([\d.]+) inlier distances \(more than 5 deg or ([\d.]+)\)", warning)
    moved, bound = float(found[1]), float(found[2])
    assert bound == pytest.approx(spacing, rel=0.01) and moved > bound, warning
