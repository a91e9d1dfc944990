"""Sensor training pairs (model.sensor_pairs), the ``real`` recipe, and a tiny training run with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree
from shapes import sphere_shapes
from tiny_training import TINY_MODEL, tiny_training_data

from model.data import PairProtocol, TrainPairStream
from model.recipes import recipe_draw
from model.sensor_pairs import (
    SensorProtocol,
    build_scene,
    random_rotations,
    sample_to_count,
    sensor_pairs,
    validation_pairs,
)
from model.sensor_sim import SensorEffects, estimate_normals
from model.train import TrainOptions, train


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def test_rotations_stay_within_the_largest_angle_and_are_haar_at_180() -> None:
    rng = np.random.default_rng(0)
    small = random_rotations(rng, 2000, 30.0)
    assert np.allclose(small @ small.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(small), 1.0)
    assert rotation_angles_deg(small).max() <= 30.0 + 1e-6
    haar = np.radians(rotation_angles_deg(random_rotations(rng, 40000, 180.0)))
    assert abs(haar.mean() - (np.pi / 2 + 2 / np.pi)) < 0.02  # the Haar measure's mean rotation angle


def test_a_scene_holds_a_floor_walls_and_objects_standing_on_it() -> None:
    rng = np.random.default_rng(1)
    objects = [s.astype(np.float64) for s in sphere_shapes(3, seed=1)]
    points, normals, half, centres = build_scene(objects, [estimate_normals(s) for s in objects], rng)
    assert points.shape == normals.shape
    planes, plane_normals = points[3 * 1024 :], normals[3 * 1024 :]  # the objects come first
    floor = np.abs(planes[:, 2]) < 1e-9
    wall = np.abs(planes[:, 1] - half) < 1e-9
    assert (floor | wall | (np.abs(planes[:, 0] - half) < 1e-9)).all()
    assert floor.sum() > 500 and wall.sum() > 300
    assert np.allclose(plane_normals[floor], [0, 0, 1]) and np.allclose(plane_normals[wall], [0, -1, 0])
    objects_part = points[: 3 * 1024]
    assert len(centres) == 3 and objects_part[:, 2].min() > -1e-9  # on the floor, not through it
    assert np.abs(objects_part[:, :2]).max() < half  # inside the room
    radii = [np.linalg.norm(objects_part[i * 1024 : (i + 1) * 1024] - c, axis=1).max() for i, c in enumerate(centres)]
    assert all(0.2 < r < 0.7 for r in radii)


@pytest.mark.parametrize("kind", ["object", "scene"])
@pytest.mark.parametrize("sampling", ["random", "spread"])
def test_sensor_pairs_have_fixed_counts_overlap_under_the_true_pose_and_are_seeded(kind: str, sampling: str) -> None:
    shapes = sphere_shapes(4, seed=2) * np.array([1.0, 0.7, 0.5], dtype=np.float32)
    effects = SensorEffects(relative_noise=0.0, mixed_share=0.0, half_angle_deg=35.0 if kind == "scene" else 180.0)
    protocol = SensorProtocol(kind=kind, source_points=300, target_points=260, max_angle_deg=90.0, sampling=sampling,
                              view_angle_deg=20.0, effects=effects)
    pairs = sensor_pairs(shapes, protocol, np.random.default_rng(3))
    assert pairs["source"].shape == (4, 300, 3) and pairs["target"].shape == (4, 260, 3)
    assert all(v.dtype == np.float32 for v in pairs.values())
    assert rotation_angles_deg(pairs["rotation"]).max() <= 90.0 + 1e-3
    src, R, t = pairs["source"], pairs["rotation"], pairs["translation"]
    rms = np.sqrt(((src - src.mean(axis=1, keepdims=True)) ** 2).sum(-1).mean(-1))
    assert np.allclose(rms, protocol.radius, rtol=1e-4)
    moved = src @ R.transpose(0, 2, 1) + t[:, None]  # the source in the target's frame
    partnered = [np.mean(cKDTree(tgt).query(m)[0] < 0.05) for m, tgt in zip(moved, pairs["target"], strict=True)]
    assert min(partnered) > 0.1, partnered  # two views of one object / scene overlap
    again = sensor_pairs(shapes, protocol, np.random.default_rng(3))
    assert all(np.array_equal(pairs[k], again[k]) for k in pairs)


def test_sample_to_count_pads_short_views_with_jittered_repeats() -> None:
    rng = np.random.default_rng(4)
    few = rng.normal(size=(50, 3))
    padded = sample_to_count(few, 80, "random", rng)
    assert padded.shape == (80, 3) and np.array_equal(padded[:50], few)
    assert len(np.unique(padded, axis=0)) == 80
    assert sample_to_count(rng.normal(size=(500, 3)), 80, "spread", rng).shape == (80, 3)


def test_the_real_recipe_mixes_general_and_sensor_batches_at_any_orientation() -> None:
    draw = recipe_draw("real")
    protocols = [draw(np.random.default_rng([5, i])) for i in range(300)]
    sensor = [p for p in protocols if isinstance(p, SensorProtocol)]
    assert 0.5 < len(sensor) / len(protocols) < 0.7
    assert {p.kind for p in sensor} == {"object", "scene"} and {p.sampling for p in sensor} == {"random", "spread"}
    assert all(p.max_angle_deg == 180.0 for p in protocols)
    general = [recipe_draw("general")(np.random.default_rng([5, i])) for i in range(50)]
    assert all(isinstance(p, PairProtocol) and p.max_angle_deg == 60.0 for p in general)  # general unchanged
    assert all(isinstance(p, PairProtocol) for p in
               (recipe_draw("real", sensor_share=0.0)(np.random.default_rng([5, i])) for i in range(50)))
    with pytest.raises(ValueError, match="sensor_share"):
        recipe_draw("real", sensor_share=1.5)


def test_a_stream_of_the_real_recipe_gives_fixed_shape_batches() -> None:
    stream = TrainPairStream(sphere_shapes(12, seed=6), recipe_draw("real", sensor_share=1.0), seed=7)
    for batch in stream.epoch(0, 4):
        assert batch["source"].ndim == 3 and batch["source"].shape[0] == 4
        assert batch["target"].shape[0] == 4 and batch["rotation"].shape == (4, 3, 3)
        assert 384 <= batch["source"].shape[1] <= 768 and 384 <= batch["target"].shape[1] <= 768


def test_the_search_recipe_draws_the_searchs_clouds_within_65_degrees() -> None:
    draw = recipe_draw("search")
    protocols = [draw(np.random.default_rng([6, i])) for i in range(200)]
    assert {type(p) for p in protocols} == {PairProtocol, SensorProtocol}
    assert all(p.source_points == 128 and p.target_points == 128 for p in protocols)
    assert all(p.max_angle_deg == 65.0 for p in protocols)
    stream = TrainPairStream(sphere_shapes(12, seed=6), draw, seed=7)
    for batch in stream.epoch(0, 4):
        assert batch["source"].shape[1:] == (128, 3) and batch["target"].shape[1:] == (128, 3)


def test_validation_pairs_alternate_objects_and_scenes_with_fixed_counts() -> None:
    pairs = validation_pairs(sphere_shapes(20, seed=8), seed=0, counts=256, chunk=8)
    assert pairs["source"].shape == (20, 256, 3) and pairs["target"].shape == (20, 256, 3)
    again = validation_pairs(sphere_shapes(20, seed=8), seed=0, counts=256, chunk=8)
    assert np.array_equal(pairs["target"], again["target"])


def test_validation_pairs_keep_to_the_training_rotations() -> None:
    angles = {}
    for limit in (30.0, 180.0):
        pairs = validation_pairs(sphere_shapes(16, seed=9), seed=0, counts=128, chunk=8, max_angle_deg=limit)
        cos = (np.trace(pairs["rotation"].astype(np.float64), axis1=1, axis2=2) - 1.0) / 2.0
        angles[limit] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))  # [16]
    assert angles[30.0].max() <= 30.0 + 1e-3 and angles[180.0].max() > 30.0, angles


@pytest.mark.parametrize("recipe", ["real", "search"])
def test_a_tiny_training_run_with_a_sensor_recipe(tmp_path, recipe: str) -> None:
    opts = TrainOptions(setting="resampled", out=str(tmp_path / "run"), data=tiny_training_data(tmp_path), epochs=1,
                        batch_size=2, max_batches_per_epoch=2, val_pairs=4, device="cpu", config=dict(TINY_MODEL),
                        recipe=recipe, sensor_share=1.0)
    best = train(opts)
    assert best.exists()
    record = json.loads((tmp_path / "run" / "log.jsonl").read_text().splitlines()[0])
    assert record["batches"] == 2 and np.isfinite(record["train_total"]) and record["val_n"] >= 1
