"""The ``scans`` setting: simulated range scans (hidden point removal, two cameras) of the dense test shapes."""

from __future__ import annotations

import numpy as np
import pytest
from pair_checks import check_indices, needs_dense
from shapes import sphere_shapes
from typer.testing import CliRunner

from model.data import PairProtocol, load_pairs, load_shapes, make_pairs, make_test_pairs, protocol_for
from model.views import CAMERA_DISTANCE, view_crop_indices, view_directions, visible_indices
from service.cli import app


def test_a_camera_sees_the_near_side_of_a_sphere_and_nothing_behind_it() -> None:
    sphere = sphere_shapes(1, 2048)[0].astype(np.float64)
    toward = np.array([0.0, 0.6, 0.8])
    seen = visible_indices(sphere, CAMERA_DISTANCE * toward)
    facing = sphere @ toward  # [N] cosine to the camera's direction; the horizon from 3 radii is at 1/3
    assert facing[seen].min() > 0.15  # nothing beyond the horizon, nothing on the far side
    assert np.isin(np.flatnonzero(facing > 0.45), seen).all()  # the whole cap well inside the horizon
    assert np.array_equal(seen, np.sort(seen))


def test_a_surface_hidden_behind_a_nearer_one_is_removed() -> None:
    rng = np.random.default_rng(0)
    near = np.c_[rng.uniform(-1, 1, (1500, 2)), np.zeros(1500)]  # [1500, 3] a square at z = 0
    far = np.c_[rng.uniform(-0.5, 0.5, (500, 2)), np.full(500, -0.5)]  # [500, 3] a smaller one right below it
    seen = visible_indices(np.vstack([near, far]), np.array([0.0, 0.0, 3.0]))
    assert np.isin(np.arange(1500), seen).all()
    assert not np.isin(np.arange(1500, 2000), seen).any()
    seen_from_below = visible_indices(np.vstack([near, far]), np.array([0.0, 0.0, -3.0]))
    assert np.isin(np.arange(1500, 2000), seen_from_below).all()  # the small square now hides part of the big one
    assert np.isin(np.arange(1500), seen_from_below).mean() < 0.9


@pytest.mark.parametrize("max_angle", [0.0, 30.0, 120.0])
def test_the_target_camera_is_turned_from_the_source_camera_by_up_to_the_view_angle(max_angle: float) -> None:
    source, target = view_directions(np.random.default_rng(1), 2000, max_angle)
    np.testing.assert_allclose(np.linalg.norm(source, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(target, axis=1), 1.0, atol=1e-12)
    angles = np.degrees(np.arccos(np.clip((source * target).sum(1), -1.0, 1.0)))  # [2000]
    assert angles.max() <= max_angle + 1e-5  # arccos near 1: ~1e-6 deg of round-off
    assert angles.max() >= 0.98 * max_angle and abs(np.median(angles) - max_angle / 2) < 0.05 * max_angle + 1e-5
    assert np.abs(source.mean(axis=0)).max() < 0.1  # source directions cover the sphere


def test_a_view_showing_too_few_points_is_filled_with_the_hidden_points_nearest_the_camera() -> None:
    sphere = sphere_shapes(1, 600)[:, :, :].astype(np.float64)  # [1, 600, 3]
    toward = np.array([[0.0, 0.0, 1.0]])
    centres, radii = np.zeros((1, 3)), np.ones(1)
    seen = visible_indices(sphere[0], CAMERA_DISTANCE * toward[0])
    kept, hidden = view_crop_indices(sphere, centres, radii, toward, len(seen) + 40, np.random.default_rng(0))
    assert hidden.tolist() == [40] and kept.shape == (1, len(seen) + 40)
    filled = np.setdiff1d(kept[0], seen)
    rest = np.setdiff1d(np.arange(600), kept[0])
    assert len(filled) == 40 and sphere[0, filled, 2].min() >= sphere[0, rest, 2].max()  # nearest the camera first
    kept, hidden = view_crop_indices(sphere, centres, radii, toward, len(seen) - 10, np.random.default_rng(0))
    assert hidden.tolist() == [0] and np.isin(kept[0], seen).all()
    with pytest.raises(ValueError, match="keep"):
        view_crop_indices(sphere, centres, radii, toward, 601, np.random.default_rng(0))


def test_scans_pairs_are_two_disjoint_views_of_512_points_each() -> None:
    shapes = sphere_shapes(4, 4096, seed=3)
    protocol = protocol_for("scans", view_angle=40)
    assert protocol == PairProtocol(points=2048, keep=512, sampling="disjoint", crop="views", view_angle_deg=40)
    pairs = make_pairs(shapes, protocol, np.random.default_rng(2), return_indices=True)
    assert pairs["source"].shape == pairs["target"].shape == (4, 512, 3)
    check_indices(shapes, pairs, disjoint=True)
    assert (pairs["source_hidden"] == 0).all() and (pairs["target_hidden"] == 0).all()  # a sphere shows ~1/3
    for b in range(4):
        for name in ("source", "target"):
            facing = shapes[b, pairs[f"{name}_index"][b]] @ pairs[f"{name}_view"][b]  # [512]
            assert facing.min() > 0.15  # every point faces its own camera (the shapes are centred unit spheres)
        angle = np.degrees(np.arccos(pairs["source_view"][b] @ pairs["target_view"][b]))
        assert angle <= 40 + 1e-5
    again = make_pairs(shapes, protocol, np.random.default_rng(2))
    for key in ("source", "target", "rotation", "translation"):
        np.testing.assert_array_equal(again[key], pairs[key])


@pytest.mark.parametrize(
    ("setting", "options", "message"),
    [("scans", {"overlap": 0.75}, "view_angle"), ("dense", {"view_angle": 30}, "scans"),
     ("scans", {"view_angle": 181}, "view_angle"), ("scans", {"source_points": 513}, "source_points")],
)
def test_scans_options_out_of_place_or_range_are_rejected(setting: str, options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        protocol_for(setting, **options)


def test_the_views_crop_leaves_the_far_point_settings_untouched() -> None:
    with pytest.raises(ValueError, match="crop"):
        PairProtocol(crop="sideways").check()
    shapes = sphere_shapes(3, 2048)
    a = make_pairs(shapes, protocol_for("dense"), np.random.default_rng(7), return_indices=True)
    assert "source_view" not in a


@needs_dense
def test_scans_test_pairs_are_seeded_views_of_the_dense_shapes(tmp_path) -> None:
    with pytest.raises(ValueError, match="test split only"):
        load_shapes("train", "scans")
    out = tmp_path / "scans.npz"
    result = CliRunner().invoke(app, ["make-pairs", "--setting", "scans", "--count", "5", "--seed", "1", "--view-angle",
                                 "30", "--out", str(out)])
    assert result.exit_code == 0, result.output
    pairs = load_pairs(out)
    expected = make_test_pairs("scans", count=5, seed=1, protocol=protocol_for("scans", view_angle=30),
                               return_indices=True)
    for key in ("source", "target", "rotation", "translation", "label"):
        np.testing.assert_array_equal(pairs[key], expected[key])
    assert pairs["source"].shape == (5, 512, 3)
    shapes = load_shapes("test", "scans")[0][expected["shape_index"]]
    check_indices(shapes, expected, disjoint=True)
