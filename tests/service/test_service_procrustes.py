"""Specification of the numpy weighted Procrustes (``service.procrustes``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.procrustes import compose, to_matrix, weighted_procrustes


def random_pose(seed: int, batch: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """``R (*batch, 3, 3)`` uniformly random rotations and ``t (*batch, 3)``."""
    count = int(np.prod(batch)) if batch else 1
    R = Rotation.random(count, random_state=seed).as_matrix().reshape(*batch, 3, 3)
    t = np.random.default_rng(seed).normal(size=(*batch, 3)) * 3
    return R, t


def transform(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...kj->...ki", R, points) + t[..., None, :]


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("centroid", ["weighted", "unweighted"])
def test_recovers_random_known_rotations(seed: int, centroid: str) -> None:
    R, t = random_pose(seed, batch=(4,))
    src = np.random.default_rng(seed + 100).normal(size=(4, 64, 3))
    R_found, t_found = weighted_procrustes(src, transform(src, R, t), None, centroid)
    np.testing.assert_allclose(R_found, R, atol=1e-10)
    np.testing.assert_allclose(t_found, t, atol=1e-8)


def test_float32_input_gives_float32_output_close_to_the_truth() -> None:
    R, t = random_pose(7)
    src = np.random.default_rng(7).normal(size=(128, 3)).astype(np.float32)
    tgt = transform(src, R, t).astype(np.float32)
    R_found, t_found = weighted_procrustes(src, tgt, np.ones(128, dtype=np.float32))
    assert R_found.dtype == np.float32 and t_found.dtype == np.float32
    np.testing.assert_allclose(R_found, R, atol=1e-5)
    np.testing.assert_allclose(t_found, t, atol=1e-5)


def test_reflection_is_never_returned() -> None:
    src = np.random.default_rng(8).normal(size=(50, 3))
    tgt = src * [1.0, 1.0, -1.0]  # a mirror image: the unconstrained optimum is a reflection
    src_c, tgt_c = src - src.mean(axis=0), tgt - tgt.mean(axis=0)
    U, _, Vt = np.linalg.svd(src_c.T @ tgt_c)
    assert np.linalg.det(Vt.T @ U.T) == pytest.approx(-1.0)  # plain SVD gives det -1 here
    R, _ = weighted_procrustes(src, tgt)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_reflection_guard_finds_the_best_rotation_for_nearly_planar_points() -> None:
    rng = np.random.default_rng(9)
    src = np.c_[rng.normal(size=(40, 2)), rng.normal(scale=1e-3, size=40)]
    tgt = src * [1.0, 1.0, -1.0]  # flipping a thin slab: the best rotation keeps the plane
    R, _ = weighted_procrustes(src, tgt)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:2, :2], np.eye(2), atol=1e-4)


def test_all_zero_weights_fall_back_to_uniform() -> None:
    R, t = random_pose(10)
    rng = np.random.default_rng(10)
    src = rng.normal(size=(30, 3))
    tgt = transform(src, R, t) + rng.normal(scale=0.05, size=(30, 3))
    uniform = weighted_procrustes(src, tgt, np.ones(30))
    zero = weighted_procrustes(src, tgt, np.zeros(30))
    np.testing.assert_allclose(zero[0], uniform[0], atol=1e-12)
    np.testing.assert_allclose(zero[1], uniform[1], atol=1e-12)


@pytest.mark.parametrize("scale", [1e-6, 1e-9, 1e-11])
def test_tiny_weights_give_the_same_pose_as_their_multiples(scale: float) -> None:
    """Weights summing to far less than one (credibilities of a network that trusts no pair) still average the pairs:
    exact pairs of a shift give the shift, whatever the weights' scale."""
    src = np.random.default_rng(11).normal(size=(64, 3))
    R, t = weighted_procrustes(src, src + np.array([1.0, 2.0, 3.0]), np.full(64, scale))
    np.testing.assert_allclose(R, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0], atol=1e-9)


def test_zero_weighted_outliers_are_ignored() -> None:
    R, t = random_pose(11)
    src = np.random.default_rng(11).normal(size=(40, 3))
    tgt = transform(src, R, t)
    tgt[:10] += 5.0  # outliers
    weights = np.r_[np.zeros(10), np.ones(30)]
    R_found, t_found = weighted_procrustes(src, tgt, weights, "weighted")
    np.testing.assert_allclose(R_found, R, atol=1e-8)
    np.testing.assert_allclose(t_found, t, atol=1e-6)


def test_collinear_points_still_give_a_proper_rotation() -> None:
    R, t = random_pose(12)
    direction = np.array([0.2, -0.3, 0.9])
    src = np.linspace(-2, 2, 20)[:, None] * direction
    tgt = transform(src, R, t)
    R_found, t_found = weighted_procrustes(src, tgt)
    assert np.linalg.det(R_found) == pytest.approx(1.0)
    np.testing.assert_allclose(R_found @ R_found.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(transform(src, R_found, t_found), tgt, atol=1e-8)  # the line is matched


@pytest.mark.parametrize("seed", range(3))
def test_centroid_variants_agree_with_uniform_weights(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src, tgt = rng.normal(size=(2, 3, 25, 3))  # unrelated clouds: any pose, just the same one
    weighted = weighted_procrustes(src, tgt, np.full((3, 25), 0.7), "weighted")
    unweighted = weighted_procrustes(src, tgt, np.full((3, 25), 0.7), "unweighted")
    np.testing.assert_allclose(weighted[0], unweighted[0], atol=1e-10)
    np.testing.assert_allclose(weighted[1], unweighted[1], atol=1e-10)


def test_centroid_variants_differ_with_non_uniform_weights() -> None:
    rng = np.random.default_rng(13)
    src, tgt = rng.normal(size=(2, 25, 3))
    weights = rng.uniform(size=25)
    assert not np.allclose(
        weighted_procrustes(src, tgt, weights, "weighted")[0],
        weighted_procrustes(src, tgt, weights, "unweighted")[0],
    )


def test_rejects_bad_inputs() -> None:
    with pytest.raises(ValueError, match="src and tgt"):
        weighted_procrustes(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="weights"):
        weighted_procrustes(np.zeros((5, 3)), np.zeros((5, 3)), np.ones(4))
    with pytest.raises(ValueError, match="centroid"):
        weighted_procrustes(np.zeros((5, 3)), np.zeros((5, 3)), None, "median")


def test_compose_applies_the_first_pose_then_the_second() -> None:
    (R_a, t_a), (R_b, t_b) = random_pose(14), random_pose(15)
    points = np.random.default_rng(16).normal(size=(10, 3))
    R_ab, t_ab = compose(R_b, t_b, R_a, t_a)
    np.testing.assert_allclose(
        transform(points, R_ab, t_ab), transform(transform(points, R_a, t_a), R_b, t_b)
    )


def test_to_matrix_builds_homogeneous_transforms() -> None:
    R, t = random_pose(17, batch=(2,))
    T = to_matrix(R, t)
    assert T.shape == (2, 4, 4)
    points = np.random.default_rng(17).normal(size=(2, 5, 3))
    homogeneous = np.concatenate([points, np.ones((2, 5, 1))], axis=-1)
    np.testing.assert_allclose(np.einsum("bij,bkj->bki", T, homogeneous)[..., :3], transform(points, R, t))
    np.testing.assert_array_equal(T[:, 3], [[0, 0, 0, 1]] * 2)
