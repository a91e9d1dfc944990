"""The settings beyond the paper (``resampled``, ``dense``) and the protocol options of every setting."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from pair_checks import EXACT, check_indices, moved, needs_dense, needs_modelnet
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from shapes import sphere_shapes
from tiny_training import TINY_MODEL, tiny_training_data
from typer.testing import CliRunner

from model.data import (
    DENSE_FILE,
    DENSE_TO_MAIN_AXES,
    SETTINGS,
    PairProtocol,
    TrainPairStream,
    data_dir,
    load_pairs,
    load_shapes,
    make_pairs,
    make_test_pairs,
    protocol_for,
)
from model.recipes import MIN_CLOUD_POINTS, GeneralRecipe, recipe_draw
from model.train import TrainOptions, train
from service.cli import app

# --- the settings' protocols ----------------------------------------------------------------------


def test_every_setting_has_a_protocol_and_the_paper_settings_are_unchanged() -> None:
    assert set(SETTINGS) == {"clean", "noise", "unseen", "resampled", "dense", "scans"}
    assert protocol_for("clean") == protocol_for("unseen") == PairProtocol()
    assert protocol_for("resampled") == PairProtocol(points=512, keep=384, sampling="disjoint")
    assert protocol_for("dense") == PairProtocol(points=1024, keep=768, sampling="disjoint")
    assert protocol_for("resampled").overlap == protocol_for("dense").overlap == 0.75
    assert protocol_for("clean", max_angle=45, overlap=0.75) == PairProtocol()  # the paper's values


def test_outliers_replace_a_share_of_each_cloud_inside_its_bounding_box() -> None:
    shapes = sphere_shapes(3, 2048)
    plain = make_pairs(shapes, protocol_for("dense"), np.random.default_rng(5), return_indices=True)
    noisy = make_pairs(shapes, protocol_for("dense", outliers=0.2), np.random.default_rng(5), return_indices=True)
    for name in ("rotation", "translation"):
        np.testing.assert_array_equal(noisy[name], plain[name])  # drawn last: the same pairs underneath
    for name in ("source", "target"):
        changed = (noisy[name] != plain[name]).any(axis=2)  # [B, N]
        assert (changed.sum(axis=1) == round(0.2 * 768)).all()
        assert ((noisy[f"{name}_index"] == -1) == changed).all()  # outliers have no shape point
        low, high = plain[name].min(axis=1, keepdims=True), plain[name].max(axis=1, keepdims=True)
        assert ((noisy[name] >= low) & (noisy[name] <= high)).all()  # inside the cloud's bounding box
        for cloud, out in zip(noisy[name], changed, strict=True):  # off the surface: far from every inlier
            tree = cKDTree(cloud[~out])
            inlier_spacing = tree.query(cloud[~out], k=2)[0][:, 1].mean()
            assert tree.query(cloud[out])[0].mean() > 3 * inlier_spacing
    for share in (-0.1, 0.6):
        with pytest.raises(ValueError, match="outliers"):
            protocol_for("dense", outliers=share)


def test_points_sets_the_cloud_size_before_the_crop_and_keeps_the_overlap() -> None:
    assert protocol_for("dense", points=2048) == PairProtocol(points=2048, keep=1536, sampling="disjoint")
    assert protocol_for("dense", points=2048, overlap=0.5).keep == 1024
    assert protocol_for("clean", points=1024) == PairProtocol()
    pairs = make_pairs(sphere_shapes(2, 4096), protocol_for("dense", points=2048), np.random.default_rng(0))
    assert pairs["source"].shape == pairs["target"].shape == (2, 1536, 3)
    with pytest.raises(ValueError, match="disjoint"):  # two disjoint clouds of 2049 need 4098 points per shape
        make_pairs(sphere_shapes(1, 4096), protocol_for("dense", points=2049), np.random.default_rng(0))
    with pytest.raises(ValueError, match="points"):
        protocol_for("dense", points=0)


def test_default_options_draw_exactly_the_paper_pairs() -> None:
    shapes = sphere_shapes(4)
    for setting in ("clean", "noise"):
        a = make_pairs(shapes, protocol_for(setting), np.random.default_rng(3))
        b = make_pairs(shapes, protocol_for(setting, noise=0.01 if setting == "noise" else 0.0, max_angle=45.0,
                                             overlap=0.75, source_points=768, target_points=768),
                       np.random.default_rng(3))
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize(
    ("options", "message"),
    [({"overlap": 0.4}, "overlap"), ({"overlap": 1.01}, "overlap"), ({"max_angle": 181}, "max_angle"),
     ({"noise": -0.1}, "noise"), ({"source_points": 385}, "source_points"), ({"target_points": 0}, "target_points")],
)
def test_out_of_range_options_are_rejected(options: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        protocol_for("resampled", **options)


def test_shapes_too_small_for_disjoint_samples_are_rejected() -> None:
    with pytest.raises(ValueError, match="disjoint"):
        make_pairs(sphere_shapes(1, 1000), protocol_for("dense"), np.random.default_rng(0))


# --- geometry -------------------------------------------------------------------------------------


def test_resampled_pairs_come_from_disjoint_halves_with_384_points_each() -> None:
    shapes = sphere_shapes(6)
    pairs = make_pairs(shapes, protocol_for("resampled"), np.random.default_rng(0), return_indices=True)
    assert pairs["source"].shape == pairs["target"].shape == (6, 384, 3)
    assert pairs["source_index"].max() < 1024
    check_indices(shapes, pairs, disjoint=True)


def test_the_paper_settings_share_their_points() -> None:
    shapes = sphere_shapes(3)
    pairs = make_pairs(shapes, protocol_for("clean"), np.random.default_rng(0), return_indices=True)
    assert pairs["source_index"].max() < 1024
    check_indices(shapes, pairs, disjoint=False)


def test_dense_pairs_are_two_disjoint_1024_point_samples_cropped_to_768() -> None:
    shapes = sphere_shapes(3, 4096)
    pairs = make_pairs(shapes, protocol_for("dense"), np.random.default_rng(1), return_indices=True)
    assert pairs["source"].shape == pairs["target"].shape == (3, 768, 3)
    check_indices(shapes, pairs, disjoint=True)


def test_full_overlap_keeps_each_whole_half_and_the_halves_partition_the_shape() -> None:
    shapes = sphere_shapes(3)
    pairs = make_pairs(shapes, protocol_for("resampled", overlap=1.0), np.random.default_rng(2), return_indices=True)
    assert pairs["source"].shape == pairs["target"].shape == (3, 512, 3)
    for src_idx, tgt_idx in zip(pairs["source_index"], pairs["target_index"], strict=True):
        np.testing.assert_array_equal(np.sort(np.concatenate([src_idx, tgt_idx])), np.arange(1024))


@pytest.mark.parametrize(("setting", "overlap", "count"), [("resampled", 0.5, 256), ("dense", 0.6, 614)])
def test_overlap_sets_the_fraction_kept_by_the_crop_a_half_space_cut(setting: str, overlap: float, count: int) -> None:
    shapes = sphere_shapes(4, 4096 if setting == "dense" else 1024)
    protocol = protocol_for(setting, overlap=overlap)
    assert protocol.keep == count
    pairs = make_pairs(shapes, protocol, np.random.default_rng(3), return_indices=True)
    assert pairs["source"].shape[1] == pairs["target"].shape[1] == count
    check_indices(shapes, pairs, disjoint=True)
    # the same seed with overlap 1.0 makes the same draws up to the crop: it shows each uncropped sample
    whole = make_pairs(shapes, protocol_for(setting, overlap=1.0), np.random.default_rng(3), return_indices=True)
    for b in range(4):
        sample, kept = whole["source_index"][b], pairs["source_index"][b]
        assert set(kept) <= set(sample)
        inside = np.isin(sample, kept)
        proj = shapes[b][sample] @ np.ones(3)  # along the direction of the far anchor, (1, 1, 1) s
        side = np.sign(proj[inside].mean() - proj.mean())
        assert (side * proj)[inside].min() > (side * proj)[~inside].max() - 0.01  # a half-space cut


def test_source_and_target_points_thin_the_crop_for_a_density_mismatch() -> None:
    shapes = sphere_shapes(4)
    full = make_pairs(shapes, protocol_for("resampled"), np.random.default_rng(4), return_indices=True)
    thin = make_pairs(shapes, protocol_for("resampled", source_points=192, target_points=384),
                      np.random.default_rng(4), return_indices=True)
    assert thin["source"].shape == (4, 192, 3) and thin["target"].shape == (4, 384, 3)
    check_indices(shapes, thin, disjoint=True)
    for b in range(4):  # the same crop (same draws before it), thinned: a subset of the region, not a smaller cut
        assert set(thin["source_index"][b]) < set(full["source_index"][b])
        np.testing.assert_array_equal(np.sort(thin["target_index"][b]), np.sort(full["target_index"][b]))
    dense = make_pairs(sphere_shapes(2, 4096), protocol_for("dense", source_points=384), np.random.default_rng(5))
    assert dense["source"].shape == (2, 384, 3) and dense["target"].shape == (2, 768, 3)


def euler_xyz_in_range(R: np.ndarray, max_deg: float) -> np.ndarray:
    """Whether each ``R [M, 3, 3]`` is ``Rx(a) Ry(b) Rz(c)`` with a, b, c in ``[0, max_deg]`` (either of the
    two Euler solutions, since ``b`` may exceed 90 degrees)."""
    e1 = Rotation.from_matrix(R.astype(np.float64)).as_euler("XYZ", degrees=True)  # b in [-90, 90]
    e2 = np.stack([e1[:, 0] + 180, 180 - e1[:, 1], e1[:, 2] + 180], 1)
    e2 = (e2 + 180) % 360 - 180

    def ok(e):
        e = np.where(e < -1e-3, e + 360, e)  # angles just below 0 wrap, angles near 180 may read -180
        return ((e >= -1e-3) & (e <= max_deg + 1e-3)).all(1)

    return ok(e1) | ok(e2)


@pytest.mark.parametrize("max_angle", [90.0, 180.0])
def test_max_angle_draws_each_euler_angle_uniformly_up_to_the_limit(max_angle: float) -> None:
    protocol = protocol_for("resampled", max_angle=max_angle)
    pairs = make_pairs(sphere_shapes(3000, 2), PairProtocol(points=1, keep=1, max_angle_deg=protocol.max_angle_deg),
                       np.random.default_rng(6))
    R = pairs["rotation"]
    assert euler_xyz_in_range(R, max_angle).all()
    assert not euler_xyz_in_range(R, max_angle - 20).all()  # the whole range is used
    total = np.degrees(Rotation.from_matrix(R.astype(np.float64)).magnitude())
    assert total.max() > (0.9 * max_angle if max_angle < 180 else 170.0)


def test_max_angle_45_keeps_every_angle_in_the_papers_range() -> None:
    R = make_pairs(sphere_shapes(2000, 2), PairProtocol(points=1, keep=1), np.random.default_rng(7))["rotation"]
    assert euler_xyz_in_range(R, 45.0).all()


def test_noise_option_has_sigma_and_is_clipped_at_five_sigma() -> None:
    protocol = protocol_for("resampled", noise=0.02, overlap=1.0)
    assert protocol.noise_sigma == 0.02 and protocol.noise_clip == pytest.approx(0.1)
    shapes = sphere_shapes(8)
    pairs = make_pairs(shapes, protocol, np.random.default_rng(8), return_indices=True)
    noise = pairs["source"].astype(np.float64) - np.take_along_axis(shapes, pairs["source_index"][..., None], 1)
    assert noise.std() == pytest.approx(0.02, rel=0.05)
    assert np.abs(noise).max() <= 0.1 + 1e-6
    tight = PairProtocol(points=512, keep=512, sampling="disjoint", noise_sigma=0.02, noise_clip=0.02)
    clipped = make_pairs(shapes, tight, np.random.default_rng(8), return_indices=True)  # the clip acts
    noise = clipped["source"].astype(np.float64) - np.take_along_axis(shapes, clipped["source_index"][..., None], 1)
    assert np.abs(noise).max() <= 0.02 + 1e-6 and (np.abs(noise) > 0.02 - 1e-6).mean() > 0.25


@pytest.mark.parametrize("setting", ["resampled", "dense"])
def test_same_seed_gives_identical_pairs_and_another_seed_different_ones(setting: str) -> None:
    shapes = sphere_shapes(3, 4096 if setting == "dense" else 1024)
    protocol = protocol_for(setting, noise=0.01, max_angle=90)
    a, b, c = (make_pairs(shapes, protocol, np.random.default_rng(s), return_indices=True) for s in (9, 9, 10))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
        assert not np.array_equal(a[key], c[key])


def test_target_order_does_not_leak_the_correspondence() -> None:
    shapes = sphere_shapes(2)
    pairs = make_pairs(shapes, protocol_for("resampled"), np.random.default_rng(11))
    for src, tgt, R, t in zip(pairs["source"], pairs["target"], pairs["rotation"], pairs["translation"], strict=True):
        dist, nearest = cKDTree(tgt).query(moved(src, R, t))
        close = dist < 0.1
        assert (nearest[close] == np.flatnonzero(close)).mean() < 0.05


# --- training -------------------------------------------------------------------------------------


def test_the_training_stream_draws_fresh_disjoint_halves_every_epoch() -> None:
    shapes = sphere_shapes(4)
    stream = TrainPairStream(shapes, protocol_for("resampled"), seed=0)

    def halves(epoch: int) -> dict[int, np.ndarray]:
        """Shape row -> source rows, recovered by exact match (the source is not moved)."""
        out = {}
        for batch in stream.epoch(epoch, 2):
            for src in batch["source"]:
                row = next(r for r in range(4) if (cKDTree(shapes[r]).query(src)[0] == 0).all())
                out[row] = np.sort(cKDTree(shapes[row]).query(src)[1])
        return out

    first, second = halves(0), halves(1)
    assert set(first) == set(second) == set(range(4))
    assert all(not np.array_equal(first[r], second[r]) for r in range(4))
    assert all(v.shape == (384,) for v in first.values())


def test_train_runs_with_the_resampled_setting_and_saves_its_protocol(tmp_path) -> None:
    from model.checkpoint import read_checkpoint

    folder = tiny_training_data(tmp_path)
    opts = TrainOptions(setting="resampled", out=str(tmp_path / "run"), data=folder, epochs=1, batch_size=2,
                        max_batches_per_epoch=1, val_pairs=2, device="cpu", config=TINY_MODEL, source_points=192,
                        max_angle=90.0)
    assert opts.pair_protocol() == protocol_for("resampled", source_points=192, max_angle=90.0)
    train(opts)
    saved = read_checkpoint(tmp_path / "run" / "last.pt")
    assert saved["setting"] == "resampled"
    assert saved["protocol"]["sampling"] == "disjoint" and saved["protocol"]["source_points"] == 192
    assert saved["protocol"]["max_angle_deg"] == 90.0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["source_points"] == 192


def test_dense_has_no_training_split(tmp_path) -> None:
    with pytest.raises(ValueError, match="test split only"):
        load_shapes("train", "dense", tmp_path)


# --- the dense file's axis frame ------------------------------------------------------------------


def test_dense_shapes_are_loaded_with_y_and_z_swapped(tmp_path) -> None:
    points = np.random.default_rng(0).normal(size=(2, 4096, 3)).astype(np.float16)
    np.savez(tmp_path / DENSE_FILE, points=points, labels=np.array([0, 1]))
    loaded, labels = load_shapes("test", "dense", tmp_path)
    assert DENSE_TO_MAIN_AXES == [0, 2, 1]
    np.testing.assert_array_equal(loaded, points.astype(np.float32)[..., [0, 2, 1]])
    np.testing.assert_array_equal(labels, [0, 1])


@needs_dense
def test_dense_shapes_match_the_same_ids_of_the_main_test_file_after_the_swap() -> None:
    dense, _ = load_shapes("test", "dense")
    with np.load(data_dir() / DENSE_FILE) as d:
        names = list(d["names"])
    with np.load(data_dir() / "modelnet40_test.npz") as m:
        main_names = list(m["names"])
        main = m["points"].astype(np.float32)

    def chamfer(a: np.ndarray, b: np.ndarray) -> float:
        return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())

    swapped, unswapped = [], []
    for i in range(0, len(names), 17):  # airplane, bathtub and bench ids
        j = main_names.index(names[i])
        swapped.append(chamfer(dense[i], main[j]))
        unswapped.append(chamfer(dense[i][..., [0, 2, 1]], main[j]))  # back in the file's own frame
    assert np.median(swapped) < 0.08 < 0.3 < np.median(unswapped)


@needs_dense
def test_dense_test_pairs_are_seeded_disjoint_samples_of_the_dense_shapes() -> None:
    pairs = make_test_pairs("dense", count=4, seed=0, return_indices=True)
    again = make_test_pairs("dense", count=4, seed=0)
    assert pairs["source"].shape == pairs["target"].shape == (4, 768, 3)
    assert set(np.unique(pairs["label"])) <= {0, 1, 3}  # airplane, bathtub, bench
    dense, _ = load_shapes("test", "dense")
    check_indices(dense[pairs["shape_index"]], pairs, disjoint=True)
    for key in again:
        np.testing.assert_array_equal(pairs[key], again[key])


# --- the commands ---------------------------------------------------------------------------------

runner = CliRunner()


@needs_modelnet
def test_make_pairs_writes_resampled_pairs_with_the_requested_options(tmp_path) -> None:
    out = tmp_path / "r.npz"
    args = ["make-pairs", "--setting", "resampled", "--count", "3", "--seed", "2", "--out", str(out),
            "--source-points", "192", "--overlap", "0.6", "--noise", "0.01", "--max-angle", "180"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    pairs = load_pairs(out)
    assert pairs["source"].shape == (3, 192, 3) and pairs["target"].shape == (3, 307, 3)
    protocol = protocol_for("resampled", source_points=192, overlap=0.6, noise=0.01, max_angle=180)
    expected = make_test_pairs("resampled", count=3, seed=2, protocol=protocol)
    for key in ("source", "target", "rotation", "translation", "label"):
        np.testing.assert_array_equal(pairs[key], expected[key])


def test_make_pairs_rejects_an_out_of_range_option(tmp_path) -> None:
    result = runner.invoke(app, ["make-pairs", "--setting", "resampled", "--overlap", "0.3",
                                 "--out", str(tmp_path / "x.npz")])
    assert result.exit_code != 0
    assert "overlap" in result.output


# --- independent sampling and the ``general`` training recipe ---------------------------------------


def test_independent_sampling_draws_two_separate_random_subsets() -> None:
    shapes = sphere_shapes(6)
    protocol = PairProtocol(points=768, keep=600, sampling="independent")
    pairs = make_pairs(shapes, protocol, np.random.default_rng(4), return_indices=True)
    assert pairs["source"].shape == (6, 600, 3) and pairs["target"].shape == (6, 600, 3)
    for b in range(6):
        src_idx, tgt_idx = pairs["source_index"][b], pairs["target_index"][b]
        np.testing.assert_array_equal(pairs["source"][b], shapes[b][src_idx])
        target = moved(shapes[b][tgt_idx], pairs["rotation"][b], pairs["translation"][b])
        assert np.abs(pairs["target"][b] - target).max() < EXACT
        shared = np.intersect1d(src_idx, tgt_idx).size
        assert 0 < shared < len(src_idx)  # overlapping but different subsets (expected share ~0.56 here)


def test_general_recipe_draws_protocols_within_its_ranges() -> None:
    recipe = GeneralRecipe()
    rng = np.random.default_rng(0)
    drawn = [recipe.draw(rng) for _ in range(400)]
    assert {p.sampling for p in drawn} == {"disjoint", "independent"}
    for p in drawn:
        assert p.points == (512 if p.sampling == "disjoint" else 768)
        assert recipe.overlap[0] - 1e-3 <= p.overlap <= recipe.overlap[1]
        noise = recipe.disjoint_noise if p.sampling == "disjoint" else recipe.subset_noise
        assert noise[0] <= p.noise_sigma <= noise[1] and p.noise_clip == pytest.approx(5 * p.noise_sigma)
        assert p.max_angle_deg == recipe.max_angle_deg
        assert p.source_points is None or p.target_points is None  # at most one sparser cloud
        sparse = p.source_points or p.target_points
        if sparse is not None:
            assert 0.5 * p.keep - 1 <= sparse <= 0.9 * p.keep + 1
    mismatched = sum((p.source_points or p.target_points) is not None for p in drawn) / len(drawn)
    assert 0.2 < mismatched < 0.4
    again = [recipe.draw(np.random.default_rng(0)) for _ in range(1)]
    assert again[0] == drawn[0]  # seeded


def test_recipe_draw_takes_the_rotation_range_and_rejects_unknown_names() -> None:
    assert recipe_draw("general", 90.0)(np.random.default_rng(1)).max_angle_deg == 90.0
    with pytest.raises(ValueError, match="unknown recipe"):
        recipe_draw("paper")


def test_recipe_outliers_are_drawn_last_and_within_the_given_share() -> None:
    plain, scattered = recipe_draw("general"), recipe_draw("general", outliers=0.3)
    for seed in range(50):
        p, q = plain(np.random.default_rng(seed)), scattered(np.random.default_rng(seed))
        assert p.outliers == 0.0 and 0.0 <= q.outliers <= 0.3
        assert dataclasses.replace(q, outliers=0.0) == p  # the other draws are unchanged
    opts = TrainOptions(setting="resampled", outliers=0.2)
    assert opts.pair_protocol() == protocol_for("resampled", outliers=0.2)  # validation: that share exactly


def test_recipe_views_are_drawn_last_and_keep_a_cameras_share_of_each_cloud() -> None:
    plain, viewed = recipe_draw("general"), recipe_draw("general", views_share=0.5)
    kinds = set()
    for seed in range(80):
        p, q = plain(np.random.default_rng(seed)), viewed(np.random.default_rng(seed))
        kinds.add(q.crop)
        if q.crop == "far_point":
            assert q == p  # the batches left as they were draw exactly what the recipe drew before
            continue
        assert dataclasses.replace(q, crop="far_point", keep=p.keep, view_angle_deg=60.0, source_points=p.source_points,
                                   target_points=p.target_points) == p  # every other draw unchanged
        assert 0.2 * q.points - 1 <= q.keep <= 0.3 * q.points + 1 and q.view_angle_deg == 60.0
        assert all(n is None or MIN_CLOUD_POINTS <= n <= q.keep for n in (q.source_points, q.target_points))
    assert kinds == {"far_point", "views"}
    every_view = recipe_draw("general", views_share=1.0)
    for seed in range(300):  # the sparser cloud of a view batch still holds the 64 + 64 training keypoints
        q = every_view(np.random.default_rng(seed))
        assert min(q.source_count, q.target_count) >= MIN_CLOUD_POINTS == 128
    with pytest.raises(ValueError, match="views_share"):
        recipe_draw("general", views_share=1.5)
    batches = TrainPairStream(sphere_shapes(4), recipe_draw("general", views_share=1.0), seed=0).epoch(0, 2)
    for batch in batches:  # views of 512 / 768 of a sphere's 1024 points: about a third shows
        assert batch["source"].shape[1] <= 0.3 * 768 + 1 and np.isfinite(batch["source"]).all()


def test_train_runs_with_outliers_in_its_pairs(tmp_path) -> None:
    from model.checkpoint import read_checkpoint

    opts = TrainOptions(setting="resampled", out=str(tmp_path / "run"), data=tiny_training_data(tmp_path), epochs=1,
                        batch_size=2, max_batches_per_epoch=1, val_pairs=2, device="cpu", config=TINY_MODEL,
                        recipe="general", outliers=0.3)
    train(opts)
    saved = read_checkpoint(tmp_path / "run" / "last.pt")
    assert saved["protocol"]["outliers"] == 0.3
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["outliers"] == 0.3


def test_the_training_stream_draws_one_protocol_per_batch() -> None:
    stream = TrainPairStream(sphere_shapes(16), recipe_draw("general"), seed=0)
    sizes = {(b["source"].shape, b["target"].shape) for b in stream.epoch(0, 2)}
    assert len(sizes) > 3  # different crops and densities across the epoch's batches
    first = [b["source"] for b in stream.epoch(0, 2)]
    assert all(np.array_equal(a, b) for a, b in zip(first, [b["source"] for b in stream.epoch(0, 2)], strict=True))


def test_train_runs_with_the_general_recipe_and_records_it(tmp_path) -> None:
    folder = tiny_training_data(tmp_path)
    opts = TrainOptions(setting="resampled", out=str(tmp_path / "run"), data=folder, epochs=1, batch_size=2,
                        max_batches_per_epoch=3, val_pairs=2, device="cpu", config=TINY_MODEL, recipe="general",
                        views_share=0.5)
    train(opts)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[0]["batches"] == 3 and np.isfinite(log[0]["train_total"])
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())["train"]
    assert recorded["recipe"] == "general" and recorded["views_share"] == 0.5


def test_train_command_rejects_an_unknown_recipe(tmp_path) -> None:
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "run"), "--recipe", "paper"])
    assert result.exit_code != 0 and "unknown recipe" in result.output
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "run"), "--views-share", "0.5"])
    assert result.exit_code != 0 and "--views-share and --sensor-share need --recipe" in result.output
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "run"), "--data-workers", "0"])
    assert result.exit_code != 0 and "--data-workers" in result.output
