"""``mfgnet evaluate`` (``bench.evaluate``) on a checkpoint or a classical baseline, through the one ``mfgnet`` app."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from bad_files import NOT_A_CHECKPOINT, NOT_A_FILE, NOT_A_MODEL, NOT_AN_NPZ, assert_usage_error, bad_file, bad_model
from provenance_check import assert_this_checkout
from shapes import sphere_shapes
from typer.testing import CliRunner

from model.data import PairProtocol, make_pairs, save_pairs
from service.cli import app

METRIC_KEYS = {
    "n",
    "rmse_r",
    "mae_r",
    "rmse_t",
    "mae_t",
    "iso_r_mean",
    "iso_r_median",
    "iso_t_mean",
    "iso_t_median",
    "recall_r1_t001",
    "recall_r5_t005",
    "ms_per_pair",
}

runner = CliRunner()


@pytest.fixture
def synthetic_pairs(tmp_path):
    path = tmp_path / "pairs.npz"
    save_pairs(path, make_pairs(sphere_shapes(3, 256), PairProtocol(points=256, keep=192), np.random.default_rng(0)))
    return path


def test_evaluate_writes_every_metric_to_json(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    out = tmp_path / "metrics.json"
    args = [
        "evaluate",
        "--checkpoint",
        str(tiny_checkpoint),
        "--pairs",
        str(synthetic_pairs),
        "--json",
        str(out),
        "--batch-size",
        "2",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert set(metrics) == METRIC_KEYS | {"evaluated"}
    assert metrics["n"] == 3
    assert all(np.isfinite(metrics[key]) for key in METRIC_KEYS)
    assert 0.0 <= metrics["recall_r5_t005"] <= 1.0


def test_evaluate_json_records_the_pairs_file_and_the_checkpoint(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    import torch

    from model.checkpoint import file_sha256, load_model

    out = tmp_path / "metrics.json"
    args = [
        "evaluate",
        "--checkpoint",
        str(tiny_checkpoint),
        "--pairs",
        str(synthetic_pairs),
        "--json",
        str(out),
        "--batch-size",
        "2",
        "--iterations",
        "1",
    ]
    assert runner.invoke(app, args).exit_code == 0
    evaluated = json.loads(out.read_text())["evaluated"]
    assert evaluated["pairs"] == {"file": str(synthetic_pairs), "sha256": file_sha256(synthetic_pairs)}
    assert evaluated["checkpoint"] == str(tiny_checkpoint)
    assert evaluated["checkpoint_sha256"] == file_sha256(tiny_checkpoint)
    assert (evaluated["iterations"], evaluated["keypoints"]) == (1, load_model(tiny_checkpoint).cfg.keypoints)
    assert evaluated["batch_size"] == 2
    assert (evaluated["machine"]["cpus"], evaluated["machine"]["threads"]) == (os.cpu_count(), torch.get_num_threads())
    assert_this_checkout(evaluated["provenance"])  # the checkpoint is named by its sha256: no model
    assert evaluated["provenance"]["models"] == []


def test_evaluate_json_records_the_setting_count_seed_and_protocol_of_made_pairs(
    tmp_path, tiny_checkpoint, monkeypatch
) -> None:
    folder = tmp_path / "data"
    folder.mkdir()
    np.savez(folder / "modelnet40_test.npz", points=sphere_shapes(4, seed=1), labels=np.arange(4))
    monkeypatch.setenv("MFGNET_DATA", str(folder))
    out = tmp_path / "metrics.json"
    args = [
        "evaluate",
        "--checkpoint",
        str(tiny_checkpoint),
        "--setting",
        "noise",
        "--count",
        "2",
        "--seed",
        "7",
        "--noise",
        "0.02",
        "--json",
        str(out),
        "--batch-size",
        "2",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    pairs = metrics["evaluated"]["pairs"]
    assert metrics["n"] == 2
    assert (pairs["setting"], pairs["split"], pairs["count"], pairs["seed"]) == ("noise", "test", 2, 7)
    assert pairs["protocol"]["noise_sigma"] == 0.02 and pairs["shapes"] == str(folder / "modelnet40_test.npz")


@pytest.mark.parametrize(
    "options",
    [
        ["--count", "2"],
        ["--seed", "7"],
        ["--setting", "noise"],
        ["--noise", "0.05"],
        ["--setting", "noise", "--count", "2", "--seed", "7", "--noise", "0.05"],
    ],
)
def test_evaluate_refuses_pair_making_options_with_a_pairs_file(tiny_checkpoint, synthetic_pairs, options) -> None:
    """A --pairs file is evaluated whole: --count, --seed, --setting and the pair options would be ignored."""
    result = runner.invoke(
        app, ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(synthetic_pairs), *options]
    )
    named = [option for option in options if option.startswith("--")]
    assert_usage_error(result, ", ".join(named) + ": cannot apply with --pairs", "make-pairs --count")


def test_evaluate_writes_per_pair_poses_and_errors(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    out, per_pair = tmp_path / "metrics.json", tmp_path / "pairs_out.npz"
    args = [
        "evaluate",
        "--checkpoint",
        str(tiny_checkpoint),
        "--pairs",
        str(synthetic_pairs),
        "--json",
        str(out),
        "--per-pair",
        str(per_pair),
        "--batch-size",
        "2",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    rows = np.load(per_pair)
    assert rows["rotation"].shape == (3, 3, 3) and rows["translation"].shape == (3, 3)
    gt = np.load(synthetic_pairs)
    expected = np.degrees(
        np.arccos(np.clip((np.einsum("mij,mij->m", rows["rotation"], gt["rotation"]) - 1) / 2, -1, 1))
    )  # angle of R^T R_gt
    np.testing.assert_allclose(rows["rotation_error_deg"], expected, atol=1e-3)
    np.testing.assert_allclose(
        rows["translation_error"], np.linalg.norm(rows["translation"] - gt["translation"], axis=1), atol=1e-6
    )
    metrics = json.loads(out.read_text())  # the pooled figures are the same errors
    assert metrics["iso_r_median"] == pytest.approx(float(np.median(rows["rotation_error_deg"])), abs=1e-3)


def test_evaluate_reports_recall_by_label(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    labelled = tmp_path / "labelled.npz"
    save_pairs(labelled, {**dict(np.load(synthetic_pairs)), "label": np.array([7, 3, 7])})
    out = tmp_path / "metrics.json"
    args = [
        "evaluate",
        "--checkpoint",
        str(tiny_checkpoint),
        "--pairs",
        str(labelled),
        "--json",
        str(out),
        "--by-label",
        "--batch-size",
        "2",
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    by_label = json.loads(out.read_text())["by_label"]
    assert set(by_label) == {"3", "7"}
    assert (by_label["3"]["n"], by_label["7"]["n"]) == (1, 2)
    assert all(0.0 <= v["recall_r5_t005"] <= 1.0 for v in by_label.values())

    unlabelled = runner.invoke(app, [*args[:4], str(synthetic_pairs), "--by-label"])
    assert unlabelled.exit_code == 2
    assert "label" in unlabelled.output


def test_evaluate_without_a_checkpoint_is_a_usage_error(synthetic_pairs) -> None:
    result = runner.invoke(app, ["evaluate", "--pairs", str(synthetic_pairs)])
    assert result.exit_code != 0
    assert "checkpoint" in result.output


def test_evaluate_takes_exactly_one_method(tiny_checkpoint, synthetic_pairs) -> None:
    both = ["evaluate", "--pairs", str(synthetic_pairs), "--checkpoint", str(tiny_checkpoint), "--baseline", "fgr"]
    result = runner.invoke(app, both)
    assert result.exit_code != 0 and "exactly one" in result.output
    result = runner.invoke(app, ["evaluate", "--pairs", str(synthetic_pairs), "--baseline", "icp-only"])
    assert result.exit_code != 0 and "unknown baseline" in result.output


def broken_pairs(path, kind: str):
    """``path`` (a pairs file) rewritten with no pair, a NaN coordinate, or a rotation that is no rotation."""
    with np.load(path) as archive:
        pairs = {key: archive[key].copy() for key in archive.files}
    if kind == "empty":
        pairs = {key: value[:0] for key, value in pairs.items()}
    elif kind == "nan":
        pairs["target"][1, 7, 2] = np.nan
    else:
        pairs["rotation"][2] *= 2.0
    out = path.with_name(f"{kind}.npz")
    np.savez(out, **pairs)
    return out


@pytest.mark.parametrize(("kind", "words"), [("empty", ["holds no pair"]),
                                             ("nan", ["target of pair 1 holds NaN or infinite values"]),
                                             ("scaled", ["rotation of pair 2 is no rotation"])])
@pytest.mark.parametrize("method", ["--checkpoint", "--model"])
def test_evaluate_refuses_pairs_it_cannot_score(tiny_checkpoint, synthetic_pairs, kind, words, method) -> None:
    """No pair, a NaN or a scaled ground-truth rotation ended in tracebacks (numpy's "need at least one array to
    stack", the runtime's InputError, LinAlgError) or, for the rotation, contradictory metrics with exit 0."""
    chosen = str(tiny_checkpoint) if method == "--checkpoint" else "general"
    result = runner.invoke(app, ["evaluate", method, chosen, "--pairs", str(broken_pairs(synthetic_pairs, kind))])
    assert_usage_error(result, "--pairs", *words)


@pytest.mark.parametrize(("args", "words"), [
    (["--count", "0"], ["--count", "1"]), (["--iterations", "0"], ["--iterations"]),
    (["--keypoints", "8"], ["--keypoints"]), (["--iterations", "99"], ["--iterations"]),
    (["--batch-size", "0"], ["--batch-size"]),
])
def test_evaluate_bounds_its_counts_to_what_the_runtime_takes(tiny_checkpoint, args, words) -> None:
    """--count 0 and --batch-size 0 were tracebacks; --iterations and --keypoints out of the runtime's ranges were
    tracebacks through --model and silently replaced or recorded as given through --checkpoint."""
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(tiny_checkpoint), *args])
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and all(word in result.output for word in words), result.output


def test_a_bundled_name_wins_over_a_folder_of_that_name_in_the_working_directory(
        tmp_path, tiny_checkpoint, synthetic_pairs, monkeypatch) -> None:
    """An export's ``--out clean`` in the working directory was taken for ``--model clean`` (its results reported as
    the bundled model's) and made ``--checkpoint clean`` "a folder, not a file"; a path (``./clean``) still names it."""
    from model.checkpoint import BUNDLED_DIR, resolve_checkpoint
    from service.manifest import bundled_models_dir, model_folder

    (tmp_path / "clean").mkdir()
    monkeypatch.chdir(tmp_path)
    assert model_folder("clean") == bundled_models_dir() / "clean"
    assert model_folder("./clean") == Path("./clean") and model_folder(tmp_path / "clean") == tmp_path / "clean"
    assert resolve_checkpoint("clean") == BUNDLED_DIR / "clean.pt"
    result = runner.invoke(app, ["evaluate", "--model", "clean", "--pairs", str(synthetic_pairs),
                                 "--json", str(tmp_path / "m.json")])
    assert result.exit_code == 0, result.output
    evaluated = json.loads((tmp_path / "m.json").read_text())["evaluated"]
    assert evaluated["model"] == "clean" and evaluated["model_directory"] == str(bundled_models_dir() / "clean")
    assert_usage_error(runner.invoke(app, ["evaluate", "--model", "./clean", "--pairs", str(synthetic_pairs)]),
                       "./clean")  # the empty folder, named as a path


def test_evaluate_a_classical_baseline_on_the_same_pairs(tmp_path, monkeypatch) -> None:
    pytest.importorskip("open3d", reason="the classical baselines need the bench extra (open3d-cpu)")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # recorded as Open3D's threads (it recorded every CPU)
    shapes = np.random.default_rng(1).normal(size=(2, 2048, 3)) * [1.0, 0.6, 0.3]  # anisotropic blobs
    pairs_path, out = tmp_path / "pairs.npz", tmp_path / "fpfh.json"
    save_pairs(
        pairs_path,
        make_pairs(shapes.astype(np.float32), PairProtocol(points=2048, keep=1800), np.random.default_rng(2)),
    )
    args = ["evaluate", "--baseline", "fpfh-ransac-icp", "--pairs", str(pairs_path), "--json", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert set(metrics) == METRIC_KEYS | {"evaluated"} and metrics["n"] == 2 and metrics["ms_per_pair"] > 0
    assert metrics["evaluated"]["baseline"] == "fpfh-ransac-icp"
    assert (metrics["evaluated"]["machine"]["cpus"], metrics["evaluated"]["machine"]["threads"]) == (os.cpu_count(), 1)
    assert_this_checkout(metrics["evaluated"]["provenance"])
    assert metrics["evaluated"]["provenance"]["models"] == []


def broken_checkpoint(tiny_checkpoint, tmp_path, kind: str):
    """The tiny checkpoint with ``kind`` of damage: no 'model', no 'config', a weight missing or reshaped."""
    import torch

    data = torch.load(tiny_checkpoint, weights_only=True)
    first = next(iter(data["model"]))
    if kind in ("no-model", "no-config"):
        del data[kind.removeprefix("no-")]
    elif kind == "missing-weight":
        del data["model"][first]
    elif kind == "wrong-shape":
        data["model"][first] = torch.zeros(1)
    path = tmp_path / f"{kind}.pt"
    torch.save(data, path)
    return path


@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_A_CHECKPOINT])
def test_evaluate_rejects_a_file_that_is_not_a_checkpoint(tmp_path, synthetic_pairs, kind) -> None:
    path = bad_file(tmp_path, kind)
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(path), "--pairs", str(synthetic_pairs)])
    assert_usage_error(
        result,
        "--checkpoint",
        str(path),
        {**NOT_A_FILE, **NOT_A_CHECKPOINT}[kind] if kind != "missing" else "no checkpoint file",
    )


@pytest.mark.parametrize(
    ("kind", "problem"),
    [
        ("no-model", "no 'model'"),
        ("no-config", "no 'config'"),
        ("missing-weight", "1 weights missing"),
        ("wrong-shape", "1 of another shape"),
    ],
)
def test_evaluate_rejects_a_checkpoint_that_does_not_fit_the_network(
    tmp_path, tiny_checkpoint, synthetic_pairs, kind, problem
) -> None:
    path = broken_checkpoint(tiny_checkpoint, tmp_path, kind)
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(path), "--pairs", str(synthetic_pairs)])
    assert_usage_error(result, str(path), problem)


@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_AN_NPZ])
def test_evaluate_rejects_a_file_that_is_not_a_pairs_file(tmp_path, tiny_checkpoint, kind) -> None:
    path = bad_file(tmp_path, kind)
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(path)])
    assert_usage_error(result, "--pairs", str(path), {**NOT_A_FILE, **NOT_AN_NPZ}[kind])


def test_evaluate_rejects_a_pairs_file_without_the_pair_arrays(tmp_path, tiny_checkpoint) -> None:
    path = tmp_path / "other.npz"
    np.savez(path, points=np.zeros((2, 3)))
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(path)])
    assert_usage_error(result, "--pairs", str(path), "lacks")


@pytest.mark.parametrize("option", ["--json", "--per-pair"])
@pytest.mark.parametrize("where", ["no-folder", "file-as-folder", "folder"])
def test_evaluate_rejects_an_output_it_cannot_write_before_evaluating(
    tmp_path, tiny_checkpoint, synthetic_pairs, option, where
) -> None:
    (tmp_path / "a_file").write_text("x")
    out = {
        "no-folder": tmp_path / "nowhere" / "out",
        "file-as-folder": tmp_path / "a_file" / "out",
        "folder": tmp_path,
    }[where]
    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(synthetic_pairs), option, str(out)]
    problem = {"no-folder": "does not exist", "file-as-folder": "is not a folder", "folder": "a folder, not a file"}
    assert_usage_error(runner.invoke(app, args), option, str(out), problem[where])


@pytest.mark.parametrize("data", ["missing", "empty-folder", "not-npz", "no-points"])
def test_evaluate_rejects_a_data_folder_without_modelnet(tmp_path, tiny_checkpoint, data, monkeypatch) -> None:
    folder = tmp_path / "data"
    if data != "missing":
        folder.mkdir()
    if data == "not-npz":
        (folder / "modelnet40_test.npz").write_text("not an archive")
    elif data == "no-points":
        np.savez(folder / "modelnet40_test.npz", labels=np.zeros(2))
    problem = {
        "missing": "folder not found",
        "empty-folder": "file not found",
        "not-npz": "not an .npz archive",
        "no-points": "no 'points'",
    }[data]
    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--count", "2"]
    assert_usage_error(runner.invoke(app, [*args, "--data", str(folder)]), str(folder), problem)
    monkeypatch.setenv("MFGNET_DATA", str(folder))  # the same through the environment
    assert_usage_error(runner.invoke(app, args), str(folder), problem)


@pytest.mark.parametrize("kind", NOT_A_MODEL)
def test_evaluate_rejects_a_model_that_is_not_a_model_folder(tmp_path, synthetic_pairs, kind) -> None:
    model = bad_model(tmp_path, kind)
    result = runner.invoke(app, ["evaluate", "--model", model, "--pairs", str(synthetic_pairs)])
    assert_usage_error(result, "--model", model, NOT_A_MODEL[kind])


def test_evaluate_help_says_what_count_and_seed_make() -> None:
    result = runner.invoke(app, ["evaluate", "--help"])
    text = " ".join(result.output.split())  # as wrapped to the terminal's width
    assert result.exit_code == 0
    assert "--count <int range> pairs to make from --setting: a seeded draw" in text
    assert "--seed <int range> seed of the pairs made from --setting [default: 0; x>=0]" in text  # NumPy's seeds


@pytest.mark.parametrize(
    ("method", "options", "words"),
    [
        ("checkpoint", ["--refine", "icp"], ("--refine", "only with --model")),
        (
            "checkpoint",
            ["--rotation-search-mode", "on", "--refine-points", "512"],
            ("--refine-points, --rotation-search-mode", "only with --model"),
        ),
        ("baseline", ["--iterations", "2"], ("--iterations", "not to --baseline")),
        ("baseline", ["--batch-size", "4"], ("--batch-size", "only with --checkpoint")),
    ],
)
def test_evaluate_refuses_options_the_method_would_ignore(
    tiny_checkpoint, synthetic_pairs, method, options, words
) -> None:
    """They were accepted and ignored: --refine icp with --checkpoint evaluated the network alone."""
    chosen = ["--checkpoint", str(tiny_checkpoint)] if method == "checkpoint" else ["--baseline", "fgr"]
    result = runner.invoke(app, ["evaluate", "--pairs", str(synthetic_pairs), *chosen, *options])
    assert_usage_error(result, *words)


@pytest.mark.parametrize("command", ["evaluate", "make-pairs"])
def test_evaluate_refuses_a_count_numpy_cannot_draw_as_make_pairs_does(tmp_path, tiny_checkpoint, command) -> None:
    """The pairs made from --setting come from one function (``model.cli.setting_pairs``): a --count that cannot be
    drawn is the same usage error in both commands, not a traceback."""
    folder = tmp_path / "data"
    folder.mkdir()
    np.savez(folder / "modelnet40_test.npz", points=sphere_shapes(4, seed=3).astype(np.float32), labels=np.arange(4))
    method = ["--checkpoint", str(tiny_checkpoint)] if command == "evaluate" else ["--out", str(tmp_path / "p.npz")]
    result = runner.invoke(app, [command, *method, "--count", "-1", "--data", str(folder)])
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Invalid value for '--count': Input should be greater than or equal to 1" in result.output  # 0 too


@pytest.mark.parametrize("command", ["evaluate", "make-pairs"])
def test_a_count_beyond_the_splits_shapes_is_refused_not_recorded(tmp_path, tiny_checkpoint, command) -> None:
    """One pair per shape: --count 1000 on 4 shapes made 4 pairs, and evaluate's JSON recorded a count of 1000."""
    folder = tmp_path / "data"
    folder.mkdir()
    np.savez(folder / "modelnet40_test.npz", points=sphere_shapes(4, seed=3).astype(np.float32), labels=np.arange(4))
    method = ["--checkpoint", str(tiny_checkpoint)] if command == "evaluate" else ["--out", str(tmp_path / "p.npz")]
    result = runner.invoke(app, [command, *method, "--count", "1000", "--data", str(folder)])
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    assert "--count 1000" in result.output and "holds 4 shapes" in result.output, result.output
    ok = runner.invoke(app, [command, *method, "--count", "4", "--data", str(folder)])
    assert ok.exit_code == 0, ok.output


@pytest.mark.parametrize(("args", "words"), [
    (["--refine", "icp-plane", "--refine-points", "5"], ["--refine-points 5", "32..8192"]),
    (["--refine", "icp-plane", "--refine-points", "100000"], ["--refine-points 100000", "32..8192"]),
    (["--refine", "none", "--refine-points", "1000"], ["--refine-points", "--refine none"]),
])
def test_evaluate_checks_refine_points_before_any_pair(synthetic_pairs, args, words) -> None:
    """Out of range it was the pipeline's InputError traceback at the first pair; with --refine none it was recorded
    in `evaluated` and ignored, where mfgnet register refuses it."""
    result = runner.invoke(app, ["evaluate", "--model", "general", "--pairs", str(synthetic_pairs), *args])
    assert_usage_error(result, *words)


@pytest.mark.parametrize("method", ["checkpoint", "model"])
def test_keypoints_beyond_the_clouds_points_are_recorded_as_used(tmp_path, tiny_checkpoint, synthetic_pairs, method):
    """`--keypoints 512` on clouds of 192 points ran with 192 (every point) and was recorded as 512."""
    out = tmp_path / "metrics.json"
    chosen = ["--checkpoint", str(tiny_checkpoint)] if method == "checkpoint" else ["--model", "general"]
    result = runner.invoke(app, ["evaluate", *chosen, "--pairs", str(synthetic_pairs), "--keypoints", "512",
                                 "--json", str(out)])
    assert result.exit_code == 0, result.output
    evaluated = json.loads(out.read_text())["evaluated"]
    assert (evaluated["keypoints"], evaluated["keypoints_used"]) == (512, 192)
    assert runner.invoke(app, ["evaluate", *chosen, "--pairs", str(synthetic_pairs), "--keypoints", "64", "--json",
                               str(out)]).exit_code == 0
    assert "keypoints_used" not in json.loads(out.read_text())["evaluated"]
