"""``model.metrics``: the paper's RMSE / MAE of zyx Euler angles and translation, isotropic errors, recall."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from model.metrics import (
    euler_zyx_deg,
    recall_by_label,
    registration_metrics,
    reliability_metrics,
    rotation_angle_deg,
    warnings_by_outcome,
)

KEYS = {"n", "rmse_r", "mae_r", "rmse_t", "mae_t", "iso_r_mean", "iso_r_median", "iso_t_mean", "iso_t_median",
        "recall_r1_t001", "recall_r5_t005"}


def zyx(*angles_deg: tuple[float, float, float]) -> np.ndarray:
    return Rotation.from_euler("zyx", angles_deg, degrees=True).as_matrix()


def test_euler_zyx_deg_inverts_scipy_from_euler() -> None:
    angles = np.array([[10.0, 20.0, 30.0], [-45.0, 5.0, 170.0]])
    np.testing.assert_allclose(euler_zyx_deg(zyx(*angles)), angles, atol=1e-10)


def test_rmse_and_mae_of_euler_angles_and_translation_by_hand() -> None:
    R_gt = zyx((10, 20, 30), (0, 0, 0), (-30, 15, 40))
    R_pred = zyx((11, 18, 30), (0, 0, 3), (-30, 15, 40))  # errors (1, -2, 0), (0, 0, 3), (0, 0, 0) degrees
    t_gt = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0], [-0.4, 0.1, 0.0]])
    t_pred = t_gt + np.array([[0.01, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.0]])
    m = registration_metrics(R_pred, t_pred, R_gt, t_gt)
    assert set(m) == KEYS  # no timing without seconds
    assert m["n"] == 3
    assert m["rmse_r"] == pytest.approx(math.sqrt((1 + 4 + 9) / 9), rel=1e-9)
    assert m["mae_r"] == pytest.approx((1 + 2 + 3) / 9, rel=1e-9)
    assert m["rmse_t"] == pytest.approx(math.sqrt((0.01**2 + 0.02**2) / 9), rel=1e-9)
    assert m["mae_t"] == pytest.approx((0.01 + 0.02) / 9, rel=1e-9)
    assert m["iso_t_mean"] == pytest.approx((0.01 + 0.02) / 3, rel=1e-9)
    assert m["iso_t_median"] == pytest.approx(0.01, rel=1e-9)
    # isotropic errors: pair 0 by scipy's rotation magnitude, pair 1 a pure 3-degree turn, pair 2 none
    iso0 = np.degrees((Rotation.from_matrix(R_pred[0]).inv() * Rotation.from_matrix(R_gt[0])).magnitude())
    assert 1.0 < iso0 < 3.0
    assert m["iso_r_median"] == pytest.approx(iso0, rel=1e-6)
    assert m["iso_r_mean"] == pytest.approx((iso0 + 3.0 + 0.0) / 3, rel=1e-6)


def test_isotropic_error_of_a_10_degree_rotation_about_z() -> None:
    R_gt = zyx((25, -10, 40))
    R_pred = zyx((10, 0, 0)) @ R_gt
    assert rotation_angle_deg(R_pred, R_gt)[0] == pytest.approx(10.0, abs=1e-9)
    assert rotation_angle_deg(R_gt, R_pred)[0] == pytest.approx(10.0, abs=1e-9)
    assert rotation_angle_deg(R_gt, R_gt)[0] == pytest.approx(0.0, abs=1e-5)


def test_isotropic_error_handles_180_degrees() -> None:
    assert rotation_angle_deg(zyx((180, 0, 0)), np.eye(3)[None])[0] == pytest.approx(180.0, abs=1e-6)


def test_recall_needs_both_the_rotation_and_the_translation_under_the_thresholds() -> None:
    R_gt = np.broadcast_to(np.eye(3), (4, 3, 3))
    R_pred = zyx((0.5, 0, 0), (0.5, 0, 0), (3, 0, 0), (6, 0, 0))
    t_gt = np.zeros((4, 3))
    t_pred = np.array([[0.005, 0, 0], [0.02, 0, 0], [0.0, 0.04, 0], [0, 0, 0]])
    m = registration_metrics(R_pred, t_pred, R_gt, t_gt)
    assert m["recall_r1_t001"] == pytest.approx(1 / 4)  # only the first: < 1 deg and < 0.01
    assert m["recall_r5_t005"] == pytest.approx(3 / 4)  # the last fails on 6 deg > 5 deg


def test_euler_differences_wrap_around_180_degrees() -> None:
    R_gt = zyx((-179, 0, 0), (0, 0, 179))
    R_pred = zyx((179, 0, 0), (0, 0, -178))  # 2 and 3 degrees away, not 358 and 357
    m = registration_metrics(R_pred, np.zeros((2, 3)), R_gt, np.zeros((2, 3)))
    assert m["mae_r"] == pytest.approx((2 + 3) / 6, rel=1e-6)
    assert m["rmse_r"] == pytest.approx(math.sqrt((4 + 9) / 6), rel=1e-6)
    assert m["iso_r_mean"] == pytest.approx(2.5, rel=1e-6)


def test_perfect_predictions_have_zero_error_and_full_recall() -> None:
    R = zyx((10, 20, 30), (-40, 5, 12))
    t = np.array([[0.1, 0.2, 0.3], [-0.4, 0.0, 0.5]])
    m = registration_metrics(R.astype(np.float32), t.astype(np.float32), R, t)
    assert m["mae_r"] < 1e-3
    assert m["mae_t"] < 1e-6
    assert m["recall_r1_t001"] == m["recall_r5_t005"] == 1.0


def test_milliseconds_per_pair_from_seconds() -> None:
    R = zyx((0, 0, 0), (0, 0, 0))
    m = registration_metrics(R, np.zeros((2, 3)), R, np.zeros((2, 3)), seconds=0.5)
    assert m["ms_per_pair"] == pytest.approx(250.0)
    assert set(m) == KEYS | {"ms_per_pair"}


def test_recall_by_label_counts_each_class_by_hand() -> None:
    R_gt = np.repeat(np.eye(3)[None], 4, axis=0)  # [4, 3, 3]
    t_gt = np.zeros((4, 3))
    R_pred = R_gt.copy()
    R_pred[1] = zyx((10.0, 0.0, 0.0))  # class 2: 10 deg off -> a miss at both thresholds
    t_pred = t_gt.copy()
    t_pred[2] = (0.02, 0.0, 0.0)  # class 5: 2 cm off -> a miss at (1 deg, 1 cm) only
    names = [f"class{i}" for i in range(6)]
    by = recall_by_label(R_pred, t_pred, R_gt, t_gt, np.array([2, 2, 5, 5]), names)
    assert by == {
        "2": {"n": 2, "name": "class2", "recall_r1_t001": 0.5, "recall_r5_t005": 0.5},
        "5": {"n": 2, "name": "class5", "recall_r1_t001": 0.5, "recall_r5_t005": 1.0},
    }
    assert "name" not in recall_by_label(R_pred, t_pred, R_gt, t_gt, np.array([2, 2, 5, 9]), names)["9"]


def test_reliability_metrics_count_trusted_misses_and_doubted_hits_by_hand() -> None:
    R_gt = np.repeat(np.eye(3)[None], 4, axis=0)  # [4, 3, 3]
    t_gt = np.zeros((4, 3))
    R_pred = R_gt.copy()
    R_pred[1] = zyx((10.0, 0.0, 0.0))  # wrong
    R_pred[3] = zyx((0.0, 0.0, 30.0))  # wrong
    t_pred = t_gt.copy()
    t_pred[2] = (0.02, 0.0, 0.0)  # right at (5 deg, 5 cm)
    reliable = np.array([True, True, False, False])  # pair 1 trusted but wrong, pair 2 right but doubted
    assert reliability_metrics(R_pred, t_pred, R_gt, t_gt, reliable) == {
        "reliable_share": 0.5, "reliable_wrong_share": 0.25, "unreliable_right_share": 0.25,
    }


def test_warnings_by_outcome_counts_each_set_of_kinds_where_reliable_misled_by_hand() -> None:
    R_gt = np.repeat(np.eye(3)[None], 6, axis=0)  # [6, 3, 3]
    t_gt = np.zeros((6, 3))
    R_pred = R_gt.copy()
    R_pred[4] = zyx((10.0, 0.0, 0.0))  # wrong
    R_pred[5] = zyx((0.0, 6.0, 0.0))  # wrong
    t_pred = t_gt.copy()
    reliable = np.array([False, False, False, True, True, False])  # 0-2 right but doubted, 4 trusted but wrong
    warnings = [("weakly constrained",), ("ambiguous", "loose fit"), ("weakly constrained",), ("poor fit",), (),
                ("poor fit",)]  # 3 right and trusted, 5 wrong and doubted: counted in neither
    assert warnings_by_outcome(R_pred, t_pred, R_gt, t_gt, reliable, warnings) == {
        "right_unreliable": {"weakly constrained": 2, "ambiguous + loose fit": 1}, "wrong_reliable": {"none": 1},
    }
    assert list(warnings_by_outcome(R_pred, t_pred, R_gt, t_gt, reliable, warnings)["right_unreliable"]) == [
        "weakly constrained", "ambiguous + loose fit"]  # most frequent first


def protocol_rotations(count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations drawn as the paper's pairs are (``model.data``): angles ``[count, 3]`` (x, y, z) in radians, uniform
    in [0, 45] degrees, and ``R = Rx Ry Rz`` ``[count, 3, 3]``."""
    from model.data import euler_xyz_to_matrix

    angles = np.random.default_rng(seed).uniform(0.0, np.pi / 4, size=(count, 3))
    return angles, euler_xyz_to_matrix(angles)


def test_true_euler_angles_are_the_drawn_angles_the_authors_compare_with() -> None:
    angles, R_gt = protocol_rotations(500, seed=3)
    # the authors' test code takes the drawn (z, y, x) as the truth; we take scipy's zyx angles of R_gt
    np.testing.assert_allclose(euler_zyx_deg(R_gt), np.degrees(angles[:, ::-1]), atol=1e-9)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
@pytest.mark.parametrize("side", ["before", "after"])
@pytest.mark.parametrize("error_deg", [0.05, 3.0, 20.0])
def test_metrics_match_an_independent_scipy_computation_for_turns_about_each_axis(axis: str, side: str,
                                                                                   error_deg: float) -> None:
    angles, R_gt = protocol_rotations(400, seed=7)
    turn = Rotation.from_euler(axis, error_deg, degrees=True).as_matrix()
    R_pred = R_gt @ turn if side == "before" else turn @ R_gt  # turned about the axis before or after R_gt
    rng = np.random.default_rng(11)
    t_gt = rng.uniform(-0.5, 0.5, size=(400, 3))
    d_t = rng.normal(0.0, 0.01, size=(400, 3))
    m = registration_metrics(R_pred.astype(np.float32), (t_gt + d_t).astype(np.float32), R_gt.astype(np.float32),
                             t_gt.astype(np.float32))
    # the authors' metric: plain differences of scipy's zyx angles from the drawn ones, pooled over pairs and angles
    d_euler = Rotation.from_matrix(R_pred).as_euler("zyx", degrees=True) - np.degrees(angles[:, ::-1])
    tol = 1e-4 * max(error_deg, 1.0)  # float32 inputs
    assert m["rmse_r"] == pytest.approx(np.sqrt(np.mean(d_euler**2)), abs=tol)
    assert m["mae_r"] == pytest.approx(np.mean(np.abs(d_euler)), abs=tol)
    iso = np.degrees((Rotation.from_matrix(R_pred).inv() * Rotation.from_matrix(R_gt)).magnitude())
    assert iso == pytest.approx(np.full(400, error_deg), abs=1e-9)  # a turn of error_deg, whatever the axis or side
    assert m["iso_r_mean"] == pytest.approx(error_deg, abs=tol)
    assert m["iso_r_median"] == pytest.approx(error_deg, abs=tol)
    assert m["rmse_t"] == pytest.approx(np.sqrt(np.mean(d_t**2)), abs=1e-7)
    assert m["mae_t"] == pytest.approx(np.mean(np.abs(d_t)), abs=1e-7)
    assert m["iso_t_mean"] == pytest.approx(np.linalg.norm(d_t, axis=1).mean(), abs=1e-7)


def test_a_pose_with_nan_counts_as_infinitely_off_instead_of_ending_the_evaluation() -> None:
    """A diverged network answers NaN: scipy's ``Rotation.from_matrix`` raised, ending an evaluation or a training
    run at its validation."""
    R_gt = Rotation.from_euler("zyx", [[10, 0, 0], [0, 20, 0], [0, 0, 30]], degrees=True).as_matrix()  # [3, 3, 3]
    t_gt = np.zeros((3, 3))
    R_pred, t_pred = R_gt.copy(), t_gt.copy()
    R_pred[1] = np.nan
    t_pred[2, 0] = np.inf
    metrics = registration_metrics(R_pred, t_pred, R_gt, t_gt)
    assert metrics["non_finite"] == 2 and metrics["n"] == 3
    assert metrics["recall_r5_t005"] == pytest.approx(1 / 3)  # the one finite pose is exact
    assert metrics["mae_r"] == np.inf and metrics["iso_r_median"] == np.inf
    assert "non_finite" not in registration_metrics(R_gt, t_gt, R_gt, t_gt)
