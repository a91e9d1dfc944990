"""Specification of ``service.normalization.Normalization``: one similarity, exactly undone."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from service.normalization import Normalization
from service.procrustes import weighted_procrustes

REFERENCE_RADIUS = 0.5


def make_pair(seed: int, n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``src (n, 3)``, ``tgt = R src + t`` and the pose ``R (3, 3)``, ``t (3,)``."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * [3.0, 2.0, 1.0] + rng.normal(size=3) * 10
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.normal(size=3) * 5
    return src, src @ R.T + t, R, t


def pose_through_normalisation(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalise, solve the pose between the normalised clouds, map it back to the caller's units."""
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    R_n, t_n = weighted_procrustes(norm.apply_src(src), norm.apply_tgt(tgt))
    return norm.unnormalize_pose(R_n, t_n)


def test_fit_centres_each_cloud_and_scales_the_source_to_the_reference_radius() -> None:
    src, tgt, _, _ = make_pair(0)
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    src_n, tgt_n = norm.apply_src(src), norm.apply_tgt(tgt)
    np.testing.assert_allclose(src_n.mean(axis=0), 0, atol=1e-12)
    np.testing.assert_allclose(tgt_n.mean(axis=0), 0, atol=1e-12)
    assert np.sqrt(np.mean(np.sum(src_n**2, axis=1))) == pytest.approx(REFERENCE_RADIUS)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    factor=st.floats(1e-3, 1e3),
    offset=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
)
def test_scaling_and_offsetting_both_clouds_maps_the_pose_accordingly(
    seed: int, factor: float, offset: list[float]
) -> None:
    src, tgt, R, t = make_pair(seed)
    o = np.array(offset)
    R_found, t_found = pose_through_normalisation(factor * src + o, factor * tgt + o)
    # tgt' = factor (R src + t) + o = R src' + (factor t + o - R o)
    np.testing.assert_allclose(R_found, R, atol=1e-8)
    np.testing.assert_allclose(t_found, factor * t + o - R @ o, atol=1e-8 * max(1.0, factor * 10 + 1e3))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_normalised_clouds_do_not_depend_on_scale_and_offset(seed: int) -> None:
    src, tgt, _, _ = make_pair(seed)
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    moved = Normalization.fit(7.5 * src - 3.0, 7.5 * tgt - 3.0, REFERENCE_RADIUS)
    np.testing.assert_allclose(moved.apply_src(7.5 * src - 3.0), norm.apply_src(src), atol=1e-9)
    np.testing.assert_allclose(moved.apply_tgt(7.5 * tgt - 3.0), norm.apply_tgt(tgt), atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_pose_round_trip_is_exact(seed: int) -> None:
    src, tgt, R, t = make_pair(seed)
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    R_n, t_n = norm.normalize_pose(R, t)
    # the normalised pose relates the normalised clouds ...
    np.testing.assert_allclose(norm.apply_tgt(tgt), norm.apply_src(src) @ R_n.T + t_n, atol=1e-12)
    # ... and maps back to the caller's pose
    R_back, t_back = norm.unnormalize_pose(R_n, t_n)
    np.testing.assert_allclose(R_back, R, atol=0)
    np.testing.assert_allclose(t_back, t, rtol=1e-14, atol=1e-12)


def test_unnormalize_pose_accepts_batches() -> None:
    src, tgt, R, t = make_pair(1)
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    R_b, t_b = norm.unnormalize_pose(np.stack([R, R.T]), np.stack([t, -t]))
    assert R_b.shape == (2, 3, 3) and t_b.shape == (2, 3)
    np.testing.assert_allclose(t_b[1], norm.unnormalize_pose(R.T, -t)[1])


def test_degenerate_source_falls_back_to_the_target_scale() -> None:
    tgt = np.random.default_rng(0).normal(size=(50, 3))
    norm = Normalization.fit(np.ones((4, 3)), tgt, REFERENCE_RADIUS)
    rms = np.sqrt(np.mean(np.sum((tgt - tgt.mean(axis=0)) ** 2, axis=1)))
    assert norm.scale == pytest.approx(rms / REFERENCE_RADIUS)


def test_both_degenerate_gives_scale_one() -> None:
    norm = Normalization.fit(np.zeros((1, 3)), np.full((3, 3), 2.0), REFERENCE_RADIUS)
    assert norm.scale == 1.0
    np.testing.assert_array_equal(norm.tgt_center, [2.0, 2.0, 2.0])


def test_apply_keeps_float32() -> None:
    src, tgt, _, _ = make_pair(2)
    norm = Normalization.fit(src, tgt, REFERENCE_RADIUS)
    assert norm.apply_src(src.astype(np.float32)).dtype == np.float32
    assert norm.apply_tgt(tgt).dtype == np.float64


@pytest.mark.parametrize("radius", [0.0, -1.0, float("nan"), float("inf")])
def test_rejects_bad_reference_radius(radius: float) -> None:
    with pytest.raises(ValueError, match="reference_radius"):
        Normalization.fit(np.zeros((3, 3)), np.zeros((3, 3)), radius)


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.zeros((4, 2)), np.array([[0.0, np.inf, 0.0]])])
def test_rejects_bad_clouds(bad: np.ndarray) -> None:
    with pytest.raises(ValueError):
        Normalization.fit(bad, np.zeros((3, 3)), REFERENCE_RADIUS)
