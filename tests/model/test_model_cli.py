"""The training-side ``mfgnet`` sub-commands (train, make-pairs) through the one ``mfgnet`` app."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bad_files import NOT_A_CHECKPOINT, NOT_A_FILE, assert_usage_error, bad_file
from shapes import sphere_shapes
from tiny_training import TINY_MODEL, sigterm_in_step, tiny_training_data
from typer.testing import CliRunner

from model.data import data_dir, load_pairs, make_test_pairs
from service.cli import app

METRIC_KEYS = {"n", "rmse_r", "mae_r", "rmse_t", "mae_t", "iso_r_mean", "iso_r_median", "iso_t_mean",
               "iso_t_median", "recall_r1_t001", "recall_r5_t005", "ms_per_pair"}

needs_modelnet = pytest.mark.skipif(
    not (data_dir() / "modelnet40_test.npz").exists(),
    reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)",
)

runner = CliRunner()


def test_training_commands_are_registered_on_the_mfgnet_app() -> None:
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for name in ("train", "evaluate", "make-pairs"):
        assert name in result.output


@needs_modelnet
def test_make_pairs_writes_a_loadable_seeded_pairs_file(tmp_path, tiny_checkpoint) -> None:
    out = tmp_path / "X.npz"
    args = ["make-pairs", "--setting", "clean", "--count", "4", "--seed", "1", "--out", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    pairs = load_pairs(out)
    assert pairs["source"].shape == pairs["target"].shape == (4, 768, 3)
    assert pairs["label"].shape == (4,)
    expected = make_test_pairs("clean", count=4, seed=1)
    for key in ("source", "target", "rotation", "translation", "label"):
        np.testing.assert_array_equal(pairs[key], expected[key])

    metrics_path = tmp_path / "out.json"
    result = runner.invoke(app, ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(out),
                                 "--json", str(metrics_path)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(metrics_path.read_text())
    assert set(metrics) == METRIC_KEYS | {"evaluated"}  # the metrics and what they were measured on
    assert metrics["n"] == 4 and metrics["evaluated"]["pairs"]["file"] == str(out)


@pytest.mark.parametrize("where", ["no-folder", "file-as-folder", "folder"])
def test_make_pairs_rejects_an_out_path_it_cannot_write(tmp_path, where) -> None:
    (tmp_path / "a_file").write_text("x")
    out = {"no-folder": tmp_path / "nowhere" / "p.npz", "file-as-folder": tmp_path / "a_file" / "p.npz",
           "folder": tmp_path}[where]
    problem = {"no-folder": "does not exist", "file-as-folder": "is not a folder", "folder": "a folder, not a file"}
    result = runner.invoke(app, ["make-pairs", "--out", str(out), "--count", "2", "--data", tiny_test_data(tmp_path)])
    assert_usage_error(result, "--out", str(out), problem[where])


def test_make_pairs_names_the_file_it_wrote_where_npz_is_added(tmp_path) -> None:
    out = tmp_path / "x"
    result = runner.invoke(app, ["make-pairs", "--out", str(out), "--count", "2", "--data", tiny_test_data(tmp_path)])
    assert result.exit_code == 0, result.output
    assert not out.exists() and load_pairs(tmp_path / "x.npz")["source"].shape[0] == 2
    assert result.output.strip().endswith(f"pairs to {tmp_path / 'x.npz'}"), result.output
    (tmp_path / "y.npz").mkdir()  # what would be written is a folder
    result = runner.invoke(app, ["make-pairs", "--out", str(tmp_path / "y"), "--count", "2", "--data",
                                 tiny_test_data(tmp_path)])
    assert_usage_error(result, "--out", str(tmp_path / "y.npz"), "a folder, not a file")


@pytest.mark.parametrize("data", ["missing", "empty-folder", "not-npz", "no-points"])
def test_make_pairs_rejects_a_data_folder_without_modelnet(tmp_path, data, monkeypatch) -> None:
    folder = tmp_path / "data"
    if data != "missing":
        folder.mkdir()
    if data == "not-npz":
        (folder / "modelnet40_test.npz").write_bytes(b"")
    elif data == "no-points":
        np.savez(folder / "modelnet40_test.npz", labels=np.zeros(2))
    problem = {"missing": "folder not found", "empty-folder": "file not found", "not-npz": "(empty)",
               "no-points": "no 'points'"}[data]
    args = ["make-pairs", "--out", str(tmp_path / "p.npz"), "--count", "2"]
    assert_usage_error(runner.invoke(app, [*args, "--data", str(folder)]), str(folder), problem)
    monkeypatch.setenv("MFGNET_DATA", str(folder))
    assert_usage_error(runner.invoke(app, args), str(folder), problem)
    assert not (tmp_path / "p.npz").exists()


@pytest.mark.parametrize("noise", ["inf", "1e308", "nan", "-0.1"])
@pytest.mark.parametrize("command", ["make-pairs", "train"])
def test_a_noise_no_cloud_survives_is_a_usage_error(tmp_path, command, noise) -> None:
    """`--noise inf` made clouds of non-finite points (make-pairs exit 0), or a LinAlgError / RuntimeError traceback."""
    data = tiny_training_data(tmp_path)
    out = tmp_path / ("p.npz" if command == "make-pairs" else "run")
    args = [command, "--out", str(out), "--data", data, "--noise", noise]
    if command == "make-pairs":
        args += ["--count", "2"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    assert "noise must be in 0..1" in result.output, result.output
    assert not out.exists()


@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_A_CHECKPOINT])
def test_train_rejects_an_init_file_that_is_not_a_checkpoint(tmp_path, kind) -> None:
    path = bad_file(tmp_path, kind)
    args = ["train", "--out", str(tmp_path / "run"), "--init", str(path), "--data", tiny_training_data(tmp_path)]
    problem = "no checkpoint file" if kind == "missing" else {**NOT_A_FILE, **NOT_A_CHECKPOINT}[kind]
    assert_usage_error(runner.invoke(app, args), "--init", str(path), problem)
    assert not (tmp_path / "run").exists()


def test_train_rejects_init_weights_of_another_network(tmp_path, tiny_checkpoint) -> None:
    import torch

    data = torch.load(tiny_checkpoint, weights_only=True)
    data["config"]["emb_dims"] = 64  # the weights are those of a narrower network than its config says
    torch.save(data, tiny_checkpoint)
    args = ["train", "--out", str(tmp_path / "run"), "--init", str(tiny_checkpoint), "--data",
            tiny_training_data(tmp_path)]
    assert_usage_error(runner.invoke(app, args), "--init", str(tiny_checkpoint), "do not fit", "of another shape")


def save_init_checkpoint(path) -> dict:
    """A tiny checkpoint whose network differs from the defaults beyond its weight shapes (as an import of the
    authors' weights does: target_minus_source, unweighted centroid, other keypoints, clamp, threshold); its config."""
    import torch

    from model.checkpoint import save_checkpoint
    from model.config import MFGNetConfig
    from model.network import MFGNet

    torch.manual_seed(0)
    cfg = MFGNetConfig.from_dict({**TINY_MODEL, "iterations": 2, "keypoints": 24, "feature_diff": "target_minus_source",
                                  "centroid": "unweighted", "clamp": 10.0, "match_threshold": 0.08})
    save_checkpoint(path, MFGNet(cfg))
    return cfg.to_dict()


def test_train_init_fine_tunes_the_checkpoints_own_network(tmp_path) -> None:
    network = save_init_checkpoint(tmp_path / "init.pt")
    run = tmp_path / "run"
    args = ["train", "--out", str(run), "--init-from", str(tmp_path / "init.pt"), "--data",
            tiny_training_data(tmp_path), "--epochs", "1", "--batch-size", "2", "--batches-per-epoch", "1",
            "--val-pairs", "2", "--device", "cpu"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert json.loads((run / "config.json").read_text())["model"] == network  # not the defaults' settings
    from model.checkpoint import read_checkpoint

    assert read_checkpoint(run / "best.pt")["config"] == network


def test_a_time_box_shorter_than_an_epoch_exits_0_and_resume_goes_on(tmp_path) -> None:
    """``--max-minutes`` that ends a run before its first validation exited 1 ("no best checkpoint"), though the help
    says such a run exits 0: a scheduler's ``--max-minutes`` + ``--resume`` loop saw a failure at each slot."""
    save_init_checkpoint(tmp_path / "init.pt")
    run = tmp_path / "run"
    args = ["train", "--out", str(run), "--init-from", str(tmp_path / "init.pt"), "--data",
            tiny_training_data(tmp_path), "--epochs", "1", "--batch-size", "2", "--batches-per-epoch", "50",
            "--val-pairs", "2", "--device", "cpu", "--max-minutes", "0.000001"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "--max-minutes ended the run before its first validation; --resume --out" in result.output
    assert (run / "last.pt").is_file() and not (run / "best.pt").exists()


@pytest.mark.parametrize(("flags", "named"), [
    (["--iterations", "4"], "--iterations 4 (the checkpoint's: 2)"),
    (["--share-weights"], "--share-weights True (the checkpoint's: False)"),
])
def test_train_init_refuses_flags_that_contradict_the_checkpoints_network(tmp_path, flags, named) -> None:
    save_init_checkpoint(tmp_path / "init.pt")
    args = ["train", "--out", str(tmp_path / "run"), "--init", str(tmp_path / "init.pt"), "--data",
            tiny_training_data(tmp_path), *flags]
    assert_usage_error(runner.invoke(app, args), named, "fine-tuning keeps the checkpoint's network")
    assert not (tmp_path / "run" / "config.json").exists()
    same = runner.invoke(app, [*args[:-len(flags)], "--iterations", "2", "--epochs", "1", "--batch-size", "2",
                               "--batches-per-epoch", "1", "--val-pairs", "2", "--device", "cpu"])
    assert same.exit_code == 0, same.output  # the checkpoint's own value may be given


def test_train_without_a_finite_validation_error_writes_no_best_and_fails(tmp_path, monkeypatch) -> None:
    """Every validation pose NaN, as a GPU SVD that does not raise returns for a broken batch. On the CPU no real
    cheap run gets there (a diverged network, lr 1e6, still gives finite poses; non-finite points make the SVD
    raise), so the validation's poses are replaced; training itself runs for real."""
    import numpy as np

    import model.train

    def nan_poses(model, pairs, batch_size=16):
        n = len(pairs["source"])
        return np.full((n, 3, 3), np.nan), np.full((n, 3), np.nan), 0.0

    monkeypatch.setattr(model.train, "predict_poses", nan_poses)
    run = tmp_path / "run"
    result = runner.invoke(app, ["train", "--out", str(run), "--data", tiny_training_data(tmp_path), "--epochs", "2",
                                 "--batch-size", "2", "--batches-per-epoch", "1", "--val-pairs", "2", "--device",
                                 "cpu", "--iterations", "1"])
    assert result.exit_code == 1, result.output
    assert "best checkpoint:" not in result.stdout
    assert "none of its 2 epochs had a finite validation MAE(R)" in result.stderr
    assert f"no {run / 'best.pt'} was written" in result.stderr
    assert not (run / "best.pt").exists() and (run / "last.pt").exists()


def test_train_rejects_a_damaged_last_checkpoint_to_resume(tmp_path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "last.pt").write_bytes(b"PK\x03\x04cut short")
    args = ["train", "--out", str(tmp_path / "run"), "--resume", "--data", tiny_training_data(tmp_path)]
    assert_usage_error(runner.invoke(app, args), "--resume", "last.pt", "not a PyTorch checkpoint")


def test_train_rejects_a_missing_data_folder_and_an_out_under_a_file(tmp_path) -> None:
    result = runner.invoke(app, ["train", "--out", str(tmp_path / "run"), "--data", str(tmp_path / "none")])
    assert_usage_error(result, str(tmp_path / "none"), "folder not found")
    (tmp_path / "a_file").write_text("x")
    result = runner.invoke(app, ["train", "--out", str(tmp_path / "a_file" / "run"), "--data",
                                 tiny_training_data(tmp_path)])
    assert_usage_error(result, "--out", "a_file", "is not a folder")


def test_train_refuses_an_out_folder_that_holds_a_run_unless_resumed(tmp_path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "log.jsonl").write_text('{"epoch": 0}\n')
    args = ["train", "--out", str(run), "--data", tiny_training_data(tmp_path)]
    assert_usage_error(runner.invoke(app, args), f"--out {run}: holds a run already (log.jsonl)", "pass --resume",
                       "another --out")
    assert (run / "log.jsonl").read_text() == '{"epoch": 0}\n'  # nothing appended, nothing replaced
    assert not (run / "config.json").exists()
    assert_usage_error(runner.invoke(app, [*args, "--resume"]), f"--resume {run}", "no last.pt to continue it from")


def test_train_resume_keeps_the_run_options_and_exits_143_on_sigterm(tmp_path, monkeypatch) -> None:
    from model.train import TrainOptions, train

    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    train(TrainOptions(setting="resampled", out=str(run), data=data, epochs=1, batch_size=2, max_batches_per_epoch=2,
                       val_pairs=2, device="cpu", config=dict(TINY_MODEL)))
    resume = ["train", "--out", str(run), "--data", data, "--resume"]
    line = assert_usage_error(
        runner.invoke(app, [*resume, "--seed", "9", "--setting", "clean", "--iterations", "3", "--lr", "1e-4"]),
        "--seed 9 (the run's: 0)", "--setting clean (the run's: resampled)", "--iterations 3 (the run's: 1)",
        "a resumed run keeps its options")
    assert "--lr" not in line  # given with the run's value

    sigterm_in_step(monkeypatch, 1)  # inside epoch 1: a signal is no end of the run
    stopped = runner.invoke(app, [*resume, "--epochs", "3"])  # more epochs: the run grows; the rest is the run's
    assert stopped.exit_code == 143, stopped.output
    assert "stopped on SIGTERM before the run's end (exit 143)" in stopped.stderr
    assert "best checkpoint" not in stopped.stdout
    saved = json.loads((run / "config.json").read_text())
    assert (saved["train"]["setting"], saved["train"]["seed"], saved["train"]["epochs"]) == ("resampled", 0, 3)
    assert saved["train"]["config"] == saved["model"] and saved["model"]["emb_dims"] == TINY_MODEL["emb_dims"]
    monkeypatch.undo()

    finished = runner.invoke(app, resume)  # --epochs left out: the run's 3
    assert finished.exit_code == 0, finished.output
    assert f"best checkpoint: {run / 'best.pt'}" in finished.stdout
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [(r["epoch"], r["batches"]) for r in records] == [(0, 2), (1, 2), (2, 2)]


def test_resume_without_config_json_takes_the_options_the_checkpoint_records(tmp_path) -> None:
    """scripts/device_train.py brings runs back without config.json: --resume then ran the default lr, batch size,
    recipe and batch cap, silently."""
    from model.train import TrainOptions, train

    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    train(TrainOptions(setting="resampled", out=str(run), data=data, epochs=1, batch_size=2, max_batches_per_epoch=2,
                       lr=1e-5, val_pairs=2, device="cpu", config=dict(TINY_MODEL)))
    (run / "config.json").unlink()
    resume = ["train", "--out", str(run), "--data", data, "--resume"]
    assert_usage_error(runner.invoke(app, [*resume, "--lr", "1e-3"]), "--lr 0.001 (the run's: 1e-05)")
    finished = runner.invoke(app, [*resume, "--epochs", "2"])
    assert finished.exit_code == 0, finished.output
    saved = json.loads((run / "config.json").read_text())["train"]
    assert (saved["lr"], saved["batch_size"], saved["max_batches_per_epoch"]) == (1e-5, 2, 2)
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [(r["epoch"], r["batches"]) for r in records] == [(0, 2), (1, 2)]


def tiny_test_data(tmp_path) -> str:
    """A data folder whose test split is 4 random spheres."""
    folder = tmp_path / "test_data"
    folder.mkdir(exist_ok=True)
    np.savez(folder / "modelnet40_test.npz", points=sphere_shapes(4, seed=3).astype(np.float32), labels=np.arange(4))
    return str(folder)


@pytest.mark.parametrize(("option", "value", "rule"), [
    ("--batch-size", "0", "1 or more"), ("--batch-size", "-3", "1 or more"), ("--epochs", "0", "1 or more"),
    ("--lr", "-1.0", "above 0"), ("--lr", "0.0", "above 0"), ("--lr", "nan", "above 0"), ("--lr", "inf", "finite"),
    ("--weight-decay", "-1.0", "0 or more"), ("--lr-drop-at", "-1.0", "0 or more"), ("--patience", "0", "1 or more"),
    ("--iterations", "0", "1 to 8"), ("--iterations", "9", "1 to 8"),  # 9: no exported model may run it
    ("--threads", "0", "1 or more"), ("--threads", "-1", "1 or more"),
    ("--max-minutes", "-1.0", "above 0"), ("--batches-per-epoch", "0", "1 or more"), ("--device", "foo", "auto, cpu"),
])
def test_train_rejects_an_option_out_of_range_before_writing_anything(tmp_path, option, value, rule) -> None:
    args = ["train", "--out", str(tmp_path / "run"), "--data", tiny_training_data(tmp_path), option, value]
    assert_usage_error(runner.invoke(app, args), f"{option} {value}: must be", rule)
    assert not (tmp_path / "run").exists()


def poisoned_data(tmp_path, value: float) -> str:
    """A data folder whose train and test splits are 12 spheres, shape 7 with one coordinate ``value`` (NaN, inf)."""
    folder = tmp_path / "poisoned"
    folder.mkdir()
    points = sphere_shapes(12, seed=3).astype(np.float16)
    points[7, 5, 1] = value
    for split in ("train", "test"):
        np.savez(folder / f"modelnet40_{split}.npz", points=points, labels=np.arange(12) % 4)
    return str(folder)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("command", ["train", "make-pairs", "evaluate"])
def test_training_commands_reject_shapes_with_nan_or_infinite_points_naming_them(tmp_path, tiny_checkpoint, command,
                                                                                value) -> None:
    """Before: train trained on (the crop mostly hid the point), make-pairs and evaluate dropped it silently."""
    data = poisoned_data(tmp_path, value)
    out = tmp_path / "out"
    args = {"train": ["train", "--out", str(out), "--epochs", "1", "--batch-size", "2", "--batches-per-epoch", "1",
                      "--val-pairs", "2", "--iterations", "1", "--device", "cpu"],
            "make-pairs": ["make-pairs", "--out", str(tmp_path / "p.npz")],
            "evaluate": ["evaluate", "--checkpoint", str(tiny_checkpoint), "--json", str(tmp_path / "m.json")]}[command]
    split = "train" if command == "train" else "test"
    assert_usage_error(runner.invoke(app, [*args, "--data", data]), f"{data}/modelnet40_{split}.npz",
                       "1 shape with NaN or infinite coordinates", "index 7")
    assert not (out / "config.json").exists() and not (out / "last.pt").exists()
    assert not (tmp_path / "p.npz").exists() and not (tmp_path / "m.json").exists()


def test_a_diverged_run_writes_no_best_and_fails(tmp_path) -> None:
    """At lr 1e6 the weights turn NaN; NaN credibilities fall back to uniform weights, so the validation's poses stay
    finite and the run wrote best.pt of NaN weights with a finite MAE(R), and exited 0."""
    run = tmp_path / "run"
    result = runner.invoke(app, ["train", "--out", str(run), "--data", tiny_training_data(tmp_path), "--epochs", "2",
                                 "--batch-size", "2", "--batches-per-epoch", "2", "--val-pairs", "2", "--device",
                                 "cpu", "--iterations", "1", "--lr", "1e6"])
    assert result.exit_code == 1, result.output
    assert "the network's weights hold NaN or inf (training diverged; lower --lr)" in result.stderr
    assert "none of its 2 epochs had a finite validation MAE(R) (NaN or inf) from finite weights" in result.stderr
    assert not (run / "best.pt").exists() and (run / "last.pt").exists()


def test_a_fine_tune_on_another_setting_than_its_checkpoint_says_so(tmp_path) -> None:
    """`--init` takes the network, not the setting: the README's fine-tune of `general` trained on `clean` pairs (the
    default) without a word, and its export took `clean`'s protocol."""
    first, second = tmp_path / "first", tmp_path / "second"
    data = tiny_training_data(tmp_path)
    common = ["--data", data, "--epochs", "1", "--batch-size", "2", "--batches-per-epoch", "1", "--val-pairs", "2",
              "--device", "cpu", "--iterations", "1"]
    assert runner.invoke(app, ["train", "--out", str(first), "--setting", "noise", *common]).exit_code == 0
    result = runner.invoke(app, ["train", "--out", str(second), "--init", str(first / "best.pt"), *common[:-2]])
    assert result.exit_code == 0, result.output
    assert f"note: {first / 'best.pt'} was trained on the 'noise' setting; this run trains and validates on 'clean'" \
        in result.stderr

