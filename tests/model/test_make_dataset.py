"""``mfgnet make-dataset``: a folder of one's own meshes and point clouds made into a data folder that make-pairs,
train and evaluate read as they read ModelNet40's (real files written with trimesh and the project's cloud writer)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from bad_files import assert_usage_error
from scipy.spatial import cKDTree
from tiny_training import TINY_MODEL
from typer.testing import CliRunner

from model.data import class_names, load_pairs, load_shapes
from service.cli import app
from service.pointcloud_io import write_points

runner = CliRunner()
MESH_SUFFIXES = ("obj", "stl", "off", "ply", "obj")


def write_source(src, boxes: int = 5, cylinders: int = 5, clouds: int = 4) -> None:
    """``src/box`` (2 x 1 x 1 boxes), ``src/cylinder`` (meshes of every suffix), ``src/scan cloud`` (clouds: PLY
    without faces, XYZ, NPY, PCD of 5000 points) and a README that is no shape."""
    for cls, count, make in (
        ("box", boxes, lambda i: trimesh.creation.box(extents=[2.0, 1.0, 1.0])),
        ("cylinder", cylinders, lambda i: trimesh.creation.cylinder(radius=0.5, height=1.0 + 0.2 * i)),
    ):
        (src / cls).mkdir(parents=True)
        for i in range(count):
            make(i).export(src / cls / f"{cls}{i}.{MESH_SUFFIXES[i % len(MESH_SUFFIXES)]}")
    (src / "scan cloud").mkdir()
    rng = np.random.default_rng(0)
    for i in range(clouds):
        points = rng.normal(size=(5000, 3)) * [1.0, 0.5, 0.3] + [10.0, -4.0, 2.0]
        write_points(src / "scan cloud" / f"c{i}.{('ply', 'xyz', 'npy', 'pcd')[i % 4]}", points)
    (src / "scan cloud" / "README.md").write_text("notes")


def make(src, out, *options: str):
    return runner.invoke(app, ["make-dataset", str(src), "--out", str(out), *options])


def test_make_dataset_writes_a_data_folder_the_commands_read(tmp_path) -> None:
    src, out = tmp_path / "src", tmp_path / "data"
    write_source(src)
    result = make(src, out)
    assert result.exit_code == 0, result.output
    assert "11 train and 3 test shapes of 1024 points" in result.stdout
    assert "left alone 1 file" in result.stderr  # the README
    with np.load(out / "modelnet40_train.npz") as train, np.load(out / "modelnet40_test.npz") as test:
        assert train["points"].shape == (11, 1024, 3) and train["points"].dtype == np.float32
        assert list(train["class_names"]) == list(test["class_names"]) == ["box", "cylinder", "scan cloud"]
        assert list(train["labels"]) == sorted(train["labels"]) and list(test["labels"]) == [0, 1, 2]
        names = set(train["names"]) | set(test["names"])
        assert "box/box3.ply" in names and "scan cloud/c3.pcd" in names and len(names) == 14
        points = np.concatenate([train["points"], test["points"]])
    np.testing.assert_allclose(points.mean(axis=1), 0.0, atol=1e-6)  # centred
    np.testing.assert_allclose(np.linalg.norm(points, axis=2).max(axis=1), 1.0, rtol=1e-6)  # unit ball
    assert class_names(str(out)) == ["box", "cylinder", "scan cloud"]  # a class name may hold a space
    record = json.loads((out / "dataset.json").read_text())
    assert record["classes"]["scan cloud"] == {"label": 2, "train": 3, "test": 1}

    # the dense file: the test shapes at 4096 points, in the main files' frame once load_shapes has read them
    main, labels = load_shapes("test", "clean", str(out))
    dense, dense_labels = load_shapes("test", "dense", str(out))
    assert dense.shape == (3, 4096, 3) and list(dense_labels) == list(labels)
    for shape, dense_shape in zip(main, dense, strict=True):
        assert cKDTree(dense_shape).query(shape)[0].mean() < 0.05

    for setting in ("clean", "dense", "scans"):
        pairs_file = tmp_path / f"{setting}.npz"
        result = runner.invoke(app, ["make-pairs", "--setting", setting, "--data", str(out), "--out", str(pairs_file)])
        assert result.exit_code == 0, result.output
        assert len(load_pairs(pairs_file)["source"]) == 3


def test_mesh_points_are_area_weighted_on_the_surface_and_seeded(tmp_path) -> None:
    src = tmp_path / "src"
    write_source(src, cylinders=2, clouds=2)
    assert make(src, tmp_path / "a", "--seed", "3").exit_code == 0
    assert make(src, tmp_path / "b", "--seed", "3").exit_code == 0
    assert make(src, tmp_path / "c", "--seed", "4").exit_code == 0
    first, again, other = (np.load(tmp_path / name / "modelnet40_train.npz")["points"] for name in "abc")
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    boxes = first[:4]  # label 0: the 2 x 1 x 1 boxes, scaled alike
    low, high = boxes.min(axis=1, keepdims=True), boxes.max(axis=1, keepdims=True)  # [4, 1, 3]: the box's faces
    on_face = np.isclose(boxes, low, rtol=0, atol=1e-5) | np.isclose(boxes, high, rtol=0, atol=1e-5)  # [4, 1024, 3]
    assert on_face.any(axis=2).all()  # every point on a face of its box
    # the two 1 x 1 ends hold 2 of the 10 square units: 20% of the points (per triangle uniform would give 33%)
    assert 0.15 < on_face[..., 0].mean() < 0.25


def test_split_file_names_the_test_shapes_and_float16_points_option(tmp_path) -> None:
    src, out = tmp_path / "src", tmp_path / "data"
    write_source(src, boxes=3, cylinders=2, clouds=2)
    split = tmp_path / "test.txt"
    split.write_text("# test shapes\nbox/box0.obj\nbox/box2.off\ncylinder/cylinder1.stl\nscan cloud/c0.ply\n")
    result = make(src, out, "--split-file", str(split), "--dtype", "float16", "--points", "512", "--dense-points", "0")
    assert result.exit_code == 0, result.output
    with np.load(out / "modelnet40_test.npz") as test:
        assert list(test["names"]) == ["box/box0.obj", "box/box2.off", "cylinder/cylinder1.stl", "scan cloud/c0.ply"]
        assert test["points"].shape == (4, 512, 3) and test["points"].dtype == np.float16
    assert not (out / "modelnet40_dense_test.npz").exists()

    split.write_text("box/box0.obj\nbox/nothing.obj\n")
    assert_usage_error(make(src, tmp_path / "d2", "--split-file", str(split)), "box/nothing.obj", "no shape file")
    split.write_text("box/box0.obj\n")  # no test shape for cylinder or scan cloud
    assert_usage_error(make(src, tmp_path / "d3", "--split-file", str(split)), "'cylinder'", "no test shapes")


def bad_mesh(kind: str) -> str:
    return {
        "nan": "OFF\n3 1 0\n0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n",
        "flat": "OFF\n3 1 0\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n",  # collinear: zero area
        "no-faces": "OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n",
    }[kind]


@pytest.mark.parametrize(
    ("kind", "words"),
    [
        ("nan", ("box/bad.off", "NaN")),
        ("flat", ("box/bad.off", "zero surface area")),
        ("no-faces", ("box/bad.off", "no faces")),
    ],
)
def test_a_bad_shape_is_named_or_left_out_with_skip_bad(tmp_path, kind, words) -> None:
    src = tmp_path / "src"
    write_source(src, cylinders=2, clouds=2)
    (src / "box" / "bad.off").write_text(bad_mesh(kind))
    assert_usage_error(make(src, tmp_path / "data"), *words, "--skip-bad")
    assert not (tmp_path / "data" / "modelnet40_train.npz").exists()
    result = make(src, tmp_path / "data", "--skip-bad")
    assert result.exit_code == 0, result.output
    assert "skipped 1 unusable shape" in result.stderr
    assert list(json.loads((tmp_path / "data" / "dataset.json").read_text())["skipped"]) == ["box/bad.off"]


def test_bad_source_folders_and_options_are_usage_errors(tmp_path) -> None:
    (tmp_path / "empty").mkdir()
    assert_usage_error(make(tmp_path / "empty", tmp_path / "d"), "no shape files")
    src = tmp_path / "src"
    write_source(src, boxes=1, cylinders=2, clouds=2)
    assert_usage_error(make(src, tmp_path / "d"), "class 'box': 1 usable shape", "at least 2")
    np.save(src / "scan cloud" / "few.npy", np.random.default_rng(0).normal(size=(100, 3)))
    (src / "scan cloud" / "nan.xyz").write_text("0 0 0\nnan 1 2\n1 1 1\n")
    assert_usage_error(make(src, tmp_path / "d", "--skip-bad", "--test-fraction", "1"), "--test-fraction 1.0")
    assert_usage_error(make(src, src / "inside"), "inside SRC")
    (tmp_path / "src" / "box" / "box1.obj").write_bytes((src / "box" / "box0.obj").read_bytes())
    result = make(src, tmp_path / "d", "--skip-bad")
    assert result.exit_code == 0, result.output
    skipped = json.loads((tmp_path / "d" / "dataset.json").read_text())["skipped"]
    assert "fewer than the 1024" in skipped["scan cloud/few.npy"] and "NaN" in skipped["scan cloud/nan.xyz"]
    assert_usage_error(make(src, tmp_path / "d"), "holds a data folder already", "--overwrite")
    assert make(src, tmp_path / "d", "--skip-bad", "--overwrite").exit_code == 0


def test_the_made_folder_trains_and_evaluates_by_its_class_names(tmp_path, tiny_checkpoint) -> None:
    from model.train import TrainOptions, train

    src, out = tmp_path / "src", tmp_path / "data"
    write_source(src)
    assert make(src, out, "--dense-points", "0").exit_code == 0
    run = tmp_path / "run"
    train(
        TrainOptions(
            out=str(run),
            data=str(out),
            epochs=1,
            batch_size=2,
            max_batches_per_epoch=2,
            val_pairs=2,
            device="cpu",
            config=dict(TINY_MODEL),
        )
    )
    assert (run / "best.pt").exists()

    pairs_file = tmp_path / "pairs.npz"
    assert runner.invoke(app, ["make-pairs", "--data", str(out), "--out", str(pairs_file)]).exit_code == 0
    metrics_file = tmp_path / "metrics.json"
    result = runner.invoke(
        app,
        [
            "evaluate",
            "--checkpoint",
            str(tiny_checkpoint),
            "--pairs",
            str(pairs_file),
            "--by-label",
            "--json",
            str(metrics_file),
        ],
    )  # no --data: the names come with the pairs
    assert result.exit_code == 0, result.output
    by_label = json.loads(metrics_file.read_text())["by_label"]
    assert [entry["name"] for entry in by_label.values()] == ["box", "cylinder", "scan cloud"]


def test_training_on_shapes_too_few_for_a_batch_is_a_usage_error(tmp_path) -> None:
    """Five training shapes and a batch of 8 ran every epoch without a step and exited 0 with the initial weights."""
    src, out = tmp_path / "src", tmp_path / "data"
    write_source(src, boxes=2, cylinders=2, clouds=2)
    assert make(src, out, "--dense-points", "0").exit_code == 0
    args = ["train", "--data", str(out), "--out", str(tmp_path / "run"), "--epochs", "1", "--batch-size", "8",
            "--device", "cpu"]
    assert_usage_error(runner.invoke(app, args), "make no batch of 8", "lower --batch-size")
    assert not (tmp_path / "run" / "best.pt").exists()
    # --resume of a folder that holds no run starts a new one: the same advice; $MFGNET_DATA named as such
    without_data = [arg for arg in args if arg not in ("--data", str(out))]
    result = CliRunner(env={"MFGNET_DATA": str(out)}).invoke(app, [*without_data, "--resume"])
    assert_usage_error(result, f"$MFGNET_DATA {out}", "lower --batch-size")


def test_unseen_setting_on_too_few_classes_is_a_usage_error(tmp_path) -> None:
    src, out = tmp_path / "src", tmp_path / "data"
    write_source(src, boxes=2, cylinders=2, clouds=2)
    result = make(src, out, "--dense-points", "0")
    assert "unseen setting: not available" in result.stdout
    args = ["make-pairs", "--setting", "unseen", "--data", str(out), "--out", str(tmp_path / "p.npz")]
    assert_usage_error(runner.invoke(app, args), "no shapes for setting 'unseen'", "more than 20 classes")
    assert not (tmp_path / "p.npz").exists()
