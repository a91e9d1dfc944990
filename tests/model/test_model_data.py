"""The ModelNet40 partial-overlap protocol of ``model.data``: geometry, ranges, noise, crop, seeds, files."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from shapes import sphere_shapes

from model.data import (
    NonFiniteShapesError,
    PairProtocol,
    data_dir,
    euler_xyz_to_matrix,
    load_pairs,
    load_shapes,
    make_pairs,
    make_test_pairs,
    protocol_for,
    save_pairs,
)

EXACT = 1e-5  # float32 round-off of R p + t for |p| <= 1.5
CROP_TOL = 0.01  # a far anchor at ~866 bends the half-space cut by at most ~5e-3 for |p| <= 1

needs_modelnet = pytest.mark.skipif(
    not (data_dir() / "modelnet40_test.npz").exists(),
    reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)",
)


def moved(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``R p + t`` in float64 for ``points [N, 3]``."""
    return points.astype(np.float64) @ R.astype(np.float64).T + t.astype(np.float64)


# --- geometry of a pair ---------------------------------------------------------------------------


def test_pairs_have_768_points_per_cloud_and_float32_arrays() -> None:
    pairs = make_pairs(sphere_shapes(3), PairProtocol(), np.random.default_rng(0))
    assert pairs["source"].shape == (3, 768, 3)
    assert pairs["target"].shape == (3, 768, 3)
    assert pairs["rotation"].shape == (3, 3, 3)
    assert pairs["translation"].shape == (3, 3)
    assert all(v.dtype == np.float32 for v in pairs.values())


def test_target_is_rotated_and_translated_source_where_the_crops_overlap() -> None:
    pairs = make_pairs(sphere_shapes(4), PairProtocol(), np.random.default_rng(1))
    for src, tgt, R, t in zip(pairs["source"], pairs["target"], pairs["rotation"], pairs["translation"],
                              strict=True):
        dist, _ = cKDTree(tgt).query(moved(src, R, t))
        assert (dist < EXACT).mean() > 0.6  # the two 75% crops share most points
        assert (dist > 1e-3).any()  # but not all: the overlap is partial


def test_rotation_is_proper() -> None:
    R = make_pairs(sphere_shapes(64, 8), PairProtocol(points=8, keep=8), np.random.default_rng(2))["rotation"]
    R = R.astype(np.float64)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-6)


def test_euler_xyz_to_matrix_is_rx_ry_rz() -> None:
    angles = np.random.default_rng(3).uniform(-np.pi, np.pi, size=(20, 3))
    expected = Rotation.from_euler("XYZ", angles).as_matrix()  # intrinsic x-y-z = Rx @ Ry @ Rz
    np.testing.assert_allclose(euler_xyz_to_matrix(angles), expected, atol=1e-12)


def test_rotation_angles_about_each_axis_are_in_0_to_45_degrees() -> None:
    pairs = make_pairs(sphere_shapes(2000, 8), PairProtocol(points=8, keep=8), np.random.default_rng(4))
    angles = Rotation.from_matrix(pairs["rotation"].astype(np.float64)).as_euler("XYZ", degrees=True)
    assert angles.min() >= -1e-3
    assert angles.max() <= 45.0 + 1e-3
    for axis in range(3):  # each axis spans the whole range, roughly uniformly
        assert angles[:, axis].min() < 2.0
        assert angles[:, axis].max() > 43.0
        assert abs(angles[:, axis].mean() - 22.5) < 1.5


def test_translation_is_in_minus_half_to_half() -> None:
    pairs = make_pairs(sphere_shapes(2000, 8), PairProtocol(points=8, keep=8), np.random.default_rng(5))
    t = pairs["translation"]
    assert t.min() >= -0.5
    assert t.max() <= 0.5
    assert t.min() < -0.45
    assert t.max() > 0.45


def test_target_points_are_shuffled_so_indices_do_not_leak_the_correspondence() -> None:
    pairs = make_pairs(sphere_shapes(2), PairProtocol(), np.random.default_rng(6))
    for src, tgt, R, t in zip(pairs["source"], pairs["target"], pairs["rotation"], pairs["translation"],
                              strict=True):
        same_index = np.linalg.norm(moved(src, R, t) - tgt, axis=-1) < EXACT
        assert same_index.mean() < 0.05


# --- determinism ----------------------------------------------------------------------------------


def test_same_seed_gives_identical_pairs_and_another_seed_different_ones() -> None:
    shapes = sphere_shapes(3)
    protocol = PairProtocol(noise_sigma=0.01)
    a = make_pairs(shapes, protocol, np.random.default_rng(7))
    b = make_pairs(shapes, protocol, np.random.default_rng(7))
    c = make_pairs(shapes, protocol, np.random.default_rng(8))
    for key in ("source", "target", "rotation", "translation"):
        np.testing.assert_array_equal(a[key], b[key])
        assert not np.array_equal(a[key], c[key])


# --- noise ----------------------------------------------------------------------------------------


def source_noise(sigma: float, clip: float = 0.05, seed: int = 9) -> np.ndarray:
    """Noise added to the source: without a crop (keep = points) the source keeps its point order, and the
    rotation / translation are drawn before the noise, so noisy minus clean (same seed) is the noise."""
    shapes = sphere_shapes(16)
    clean = make_pairs(shapes, PairProtocol(keep=1024), np.random.default_rng(seed))
    noisy = make_pairs(shapes, PairProtocol(keep=1024, noise_sigma=sigma, noise_clip=clip),
                       np.random.default_rng(seed))
    np.testing.assert_array_equal(clean["rotation"], noisy["rotation"])
    return noisy["source"].astype(np.float64) - clean["source"].astype(np.float64)


def test_noise_has_sigma_001_and_zero_mean() -> None:
    noise = source_noise(0.01)
    assert noise.std() == pytest.approx(0.01, rel=0.03)
    assert abs(noise.mean()) < 5e-4


def test_noise_is_clipped_at_005() -> None:
    noise = source_noise(0.05)  # sigma at the clip: about a third of the draws are clipped
    assert np.abs(noise).max() <= 0.05 + 1e-6
    at_clip = np.abs(noise) > 0.05 - 1e-6
    assert 0.25 < at_clip.mean() < 0.40


def test_noise_moves_the_target_independently_and_within_the_clip() -> None:
    shapes = sphere_shapes(4)
    clean = make_pairs(shapes, PairProtocol(keep=1024), np.random.default_rng(10))
    noisy = make_pairs(shapes, PairProtocol(keep=1024, noise_sigma=0.01), np.random.default_rng(10))
    for b in range(4):
        dist, _ = cKDTree(clean["target"][b]).query(noisy["target"][b])
        assert dist.max() <= np.sqrt(3) * 0.05 + 1e-5
        assert np.median(dist) > 0.005  # every target point moved (typical |n| ~ 0.016)


# --- crop -----------------------------------------------------------------------------------------


def kept_mask(full: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Which points of ``full [N, 3]`` survive in ``kept [K, 3]`` (exact up to float32 round-off)."""
    dist, _ = cKDTree(kept).query(full)
    return dist < EXACT


def half_space_side(full: np.ndarray, mask: np.ndarray) -> float:
    """+1 or -1: the side of ``(1, 1, 1)`` on which the kept points lie."""
    proj = full @ np.ones(3)
    return float(np.sign(proj[mask].mean() - proj.mean()))


def test_crop_keeps_the_points_nearest_the_far_anchor_the_same_cut_for_both_clouds() -> None:
    shapes = sphere_shapes(12)
    pairs = make_pairs(shapes, PairProtocol(), np.random.default_rng(11))
    sides = []
    for b in range(12):
        full_src = shapes[b].astype(np.float64)
        full_tgt = moved(shapes[b], pairs["rotation"][b], pairs["translation"][b])
        side = None
        for full, kept in ((full_src, pairs["source"][b]), (full_tgt, pairs["target"][b])):
            mask = kept_mask(full, kept)
            assert mask.sum() == 768
            s = half_space_side(full, mask)
            proj = full @ (s * np.ones(3) / np.sqrt(3))  # along the direction of the anchor
            assert proj[mask].min() > proj[~mask].max() - CROP_TOL  # a half-space cut
            assert side is None or s == side  # one anchor for source and target
            side = s
        sides.append(side)
    assert set(sides) == {-1.0, 1.0}  # the anchor side is random


# --- pairs files ----------------------------------------------------------------------------------


def test_pairs_file_round_trips(tmp_path) -> None:
    pairs = make_pairs(sphere_shapes(3), PairProtocol(), np.random.default_rng(12))
    pairs["label"] = np.array([1, 2, 3])
    save_pairs(tmp_path / "p.npz", pairs)
    loaded = load_pairs(tmp_path / "p.npz")
    assert set(loaded) == set(pairs)
    for key, value in pairs.items():
        np.testing.assert_array_equal(loaded[key], value)
        assert loaded[key].dtype == value.dtype


def good_pairs(M: int = 2) -> dict[str, np.ndarray]:
    return {
        "source": np.zeros((M, 5, 3), np.float32),
        "target": np.zeros((M, 4, 3), np.float32),
        "rotation": np.broadcast_to(np.eye(3, dtype=np.float32), (M, 3, 3)).copy(),
        "translation": np.zeros((M, 3), np.float32),
    }


def test_load_pairs_accepts_different_point_counts_and_casts_to_float32(tmp_path) -> None:
    pairs = {k: v.astype(np.float64) for k, v in good_pairs().items()}
    save_pairs(tmp_path / "p.npz", pairs)
    loaded = load_pairs(tmp_path / "p.npz")
    assert loaded["target"].shape == (2, 4, 3)
    assert all(loaded[k].dtype == np.float32 for k in pairs)


@pytest.mark.parametrize("key", ["source", "target", "rotation", "translation"])
def test_load_pairs_rejects_a_file_missing_a_key(tmp_path, key: str) -> None:
    pairs = good_pairs()
    del pairs[key]
    np.savez(tmp_path / "p.npz", **pairs)
    with pytest.raises(ValueError, match=key):
        load_pairs(tmp_path / "p.npz")


@pytest.mark.parametrize(
    ("key", "shape"),
    [
        ("source", (2, 5, 2)),
        ("source", (2, 15)),
        ("target", (3, 4, 3)),
        ("rotation", (2, 3)),
        ("rotation", (1, 3, 3)),
        ("translation", (2, 3, 1)),
        ("translation", (3, 3)),
    ],
)
def test_load_pairs_rejects_wrong_shapes(tmp_path, key: str, shape: tuple[int, ...]) -> None:
    pairs = good_pairs()
    pairs[key] = np.zeros(shape, np.float32)
    np.savez(tmp_path / "p.npz", **pairs)
    with pytest.raises(ValueError):
        load_pairs(tmp_path / "p.npz")


# --- settings -------------------------------------------------------------------------------------


def test_settings_select_noise_only_for_noise() -> None:
    assert protocol_for("clean") == PairProtocol()
    assert protocol_for("unseen") == PairProtocol()
    assert protocol_for("noise").noise_sigma == 0.01
    assert protocol_for("noise").noise_clip == 0.05


def test_unknown_setting_and_split_are_rejected() -> None:
    with pytest.raises(ValueError, match="setting"):
        protocol_for("partial")
    with pytest.raises(ValueError, match="split"):
        load_shapes("val")


def test_data_dir_prefers_an_explicit_path_then_the_environment(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("MFGNET_DATA", str(tmp_path / "env"))
    assert data_dir(tmp_path / "explicit") == tmp_path / "explicit"
    assert data_dir() == tmp_path / "env"


def test_load_shapes_names_the_missing_file(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match=r"modelnet40_test\.npz"):
        load_shapes("test", path=tmp_path)


def test_load_shapes_refuses_shapes_with_nan_or_infinite_points_naming_their_rows_in_the_file(tmp_path) -> None:
    """The rows are the file's, also for ``unseen``, which keeps some labels only; named where the file names shapes."""
    points = sphere_shapes(30, seed=3).astype(np.float16)
    points[[4, 25], 0, 2] = np.nan, -np.inf
    names = np.array([f"sphere_{i:04d}" for i in range(30)])
    np.savez(tmp_path / "modelnet40_train.npz", points=points, labels=np.arange(30) % 40, names=names)
    for setting in ("clean", "unseen"):
        with pytest.raises(NonFiniteShapesError, match=r"modelnet40_train\.npz: 2 shapes with NaN or infinite "
                           r"coordinates, at index 4 \(sphere_0004\), 25 \(sphere_0025\)") as caught:
            load_shapes("train", setting, tmp_path)
        assert caught.value.rows.tolist() == [4, 25]


# --- the real ModelNet40 files --------------------------------------------------------------------


@needs_modelnet
def test_modelnet40_splits_have_the_official_sizes() -> None:
    test_points, test_labels = load_shapes("test")
    assert test_points.shape == (2468, 1024, 3)
    assert test_points.dtype == np.float32
    assert test_labels.dtype == np.int64
    assert set(np.unique(test_labels)) == set(range(40))
    train_points, _ = load_shapes("train")
    assert train_points.shape == (9843, 1024, 3)
    assert np.abs(train_points).max() <= 1.0 + 1e-3  # normalised into the unit sphere


@needs_modelnet
def test_unseen_setting_trains_on_labels_below_20_and_tests_on_the_rest() -> None:
    _, all_test = load_shapes("test")
    points, labels = load_shapes("test", "unseen")
    assert labels.min() >= 20
    assert len(points) == len(labels) == (all_test >= 20).sum()
    _, train_labels = load_shapes("train", "unseen")
    assert train_labels.max() < 20
    assert set(np.unique(train_labels)) == set(range(20))


@needs_modelnet
@pytest.mark.parametrize("setting", ["clean", "noise", "unseen"])
def test_make_test_pairs_is_seeded_and_has_the_requested_count(setting: str) -> None:
    a = make_test_pairs(setting, count=5, seed=3)
    b = make_test_pairs(setting, count=5, seed=3)
    c = make_test_pairs(setting, count=5, seed=4)
    assert a["source"].shape == a["target"].shape == (5, 768, 3)
    assert a["label"].shape == (5,)
    for key in ("source", "target", "rotation", "translation"):
        assert a[key].dtype == np.float32
        np.testing.assert_array_equal(a[key], b[key])
        assert not np.array_equal(a[key], c[key])
    np.testing.assert_array_equal(a["label"], b["label"])
    if setting == "unseen":
        assert a["label"].min() >= 20


@needs_modelnet
def test_clean_pairs_overlap_exactly_and_noise_pairs_do_not() -> None:
    for setting, exact_fraction in (("clean", lambda f: f > 0.5), ("noise", lambda f: f == 0.0)):
        pairs = make_test_pairs(setting, count=3, seed=0)
        for src, tgt, R, t in zip(pairs["source"], pairs["target"], pairs["rotation"], pairs["translation"],
                                  strict=True):
            dist, _ = cKDTree(tgt).query(moved(src, R, t))
            assert exact_fraction((dist < EXACT).mean()), setting


@needs_modelnet
def test_all_test_pairs_when_no_count_is_given() -> None:
    pairs = make_test_pairs("unseen")
    assert len(pairs["source"]) == len(load_shapes("test", "unseen")[1])
