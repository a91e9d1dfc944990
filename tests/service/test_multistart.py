"""refine="icp-plane-multistart" (service.multistart): turned starts, short ICPs, a two-way point-to-plane score."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

from service.icp import icp_plane
from service.manifest import bundled_models_dir
from service.multistart import best_turned_pose, symmetric_plane_scores, turned_poses
from service.registrar import Registrar

BUNDLED = bundled_models_dir() / "general"

R_TRUE = Rotation.from_euler("xyz", [20.0, -10.0, 40.0], degrees=True).as_matrix()
T_TRUE = np.array([0.3, -0.2, 0.1])


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    if not (BUNDLED / "manifest.json").exists():
        pytest.skip("bundled model 'general' absent")
    return Registrar(BUNDLED, threads=1, warmup=False)


def independent_pair() -> tuple[np.ndarray, np.ndarray]:
    """Two independent samples of one asymmetric surface, the target moved by ``R_TRUE, T_TRUE``."""
    return asymmetric_blob(500, 1), asymmetric_blob(500, 2) @ R_TRUE.T + T_TRUE


def degrees_between(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R_a.T @ R_b) - 1) / 2, -1, 1))))


def test_turned_poses_turn_about_the_centre_and_keep_the_pose_first() -> None:
    centre = np.array([1.0, 2.0, 3.0])
    R_h, t_h = turned_poses(R_TRUE, T_TRUE, centre, angles_deg=(15.0, 30.0))
    assert R_h.shape == (13, 3, 3) and t_h.shape == (13, 3)
    np.testing.assert_array_equal(R_h[0], R_TRUE)
    np.testing.assert_allclose(t_h[0], T_TRUE)
    angles = sorted(round(degrees_between(R, R_TRUE), 6) for R in R_h[1:])
    assert angles == [15.0] * 6 + [30.0] * 6
    point = np.array([0.5, -0.4, 0.2])  # where R_TRUE, T_TRUE puts it, each turn keeps at the same distance from centre
    moved = np.einsum("hij,j->hi", R_h, point) + t_h
    np.testing.assert_allclose(np.linalg.norm(moved - centre, axis=1), np.linalg.norm(moved[0] - centre), atol=1e-12)


def test_the_two_way_score_prefers_the_true_pose() -> None:
    src, tgt = independent_pair()
    R_h, t_h = turned_poses(R_TRUE, T_TRUE, tgt.mean(axis=0))
    scores = symmetric_plane_scores(src, tgt, R_h, t_h, cap=0.05)
    assert int(np.argmin(scores)) == 0 and scores[0] < 0.5 * scores[1:].min()


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_pose_turned_30_degrees_is_brought_back(axis: int) -> None:
    src, tgt = independent_pair()
    turn = Rotation.from_rotvec(np.radians(30.0) * np.eye(3)[axis]).as_matrix()
    centre = tgt.mean(axis=0)
    R0, t0 = turn @ R_TRUE, turn @ (T_TRUE - centre) + centre
    R, t, start = best_turned_pose(src, tgt, R0, t0, scale=1.0)
    assert start != 0
    # the right basin (the short point-to-point ICP between independent samples stops a few degrees off) ...
    assert degrees_between(R, R_TRUE) < 6.0
    precise = icp_plane(src, tgt, R, t, max_distance=0.1)  # ... which the registrar's precise stage then closes
    assert degrees_between(precise.rotation, R_TRUE) < 1.0 and np.linalg.norm(precise.translation - T_TRUE) < 0.02


def test_register_with_multistart_keeps_a_right_pose(registrar) -> None:
    src, tgt = independent_pair()
    plane = registrar.register(src, tgt, refine="icp-plane")
    multi = registrar.register(src, tgt, refine="icp-plane-multistart")
    assert degrees_between(plane.rotation, R_TRUE) < 2.0  # the plain result is right here ...
    assert degrees_between(multi.rotation, plane.rotation) < 0.5  # ... and the multi-start keeps it
    assert multi.reliable and "refine" in multi.timing_ms


@pytest.mark.parametrize("shape", ["identical", "collinear", "planar", "32 points"])
def test_multistart_on_degenerate_or_tiny_clouds_returns_a_finite_flagged_pose(registrar, shape: str) -> None:
    rng = np.random.default_rng(5)
    src, tgt = {
        "identical": (np.ones((100, 3)), np.ones((100, 3))),
        "collinear": (np.linspace(0, 1, 200)[:, None] * [1.0, 2.0, 3.0],) * 2,
        "planar": (np.c_[rng.uniform(size=(200, 2)), np.zeros(200)], np.c_[rng.uniform(size=(200, 2)), np.zeros(200)]),
        "32 points": (rng.normal(size=(32, 3)), rng.normal(size=(40, 3))),
    }[shape]
    res = registrar.register(src, tgt, refine="icp-plane-multistart")
    assert np.isfinite(res.transform).all()
    assert res.warnings and (shape == "planar" or not res.reliable)
