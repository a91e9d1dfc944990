"""``mfgnet export`` and ``mfgnet import-checkpoint`` on bad files: a one-line usage error (exit 2), no traceback."""

from __future__ import annotations

import pytest
import torch
from bad_files import NOT_A_CHECKPOINT, NOT_A_FILE, assert_usage_error, bad_file
from tiny_training import save_tiny_checkpoint
from typer.testing import CliRunner

from service.cli import app

runner = CliRunner()


@pytest.fixture
def tiny_checkpoint(tmp_path):
    path = tmp_path / "tiny.pt"
    save_tiny_checkpoint(path)
    return path


@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_A_CHECKPOINT])
def test_export_rejects_a_file_that_is_not_a_checkpoint(tmp_path, kind) -> None:
    path = bad_file(tmp_path, kind)
    result = runner.invoke(app, ["export", "--checkpoint", str(path), "--out", str(tmp_path / "m")])
    problem = "no checkpoint file" if kind == "missing" else {**NOT_A_FILE, **NOT_A_CHECKPOINT}[kind]
    assert_usage_error(result, "--checkpoint", str(path), problem)
    assert not (tmp_path / "m").exists()


def test_export_rejects_a_checkpoint_with_a_weight_of_another_shape(tmp_path, tiny_checkpoint) -> None:
    data = torch.load(tiny_checkpoint, weights_only=True)
    data["model"][next(iter(data["model"]))] = torch.zeros(2, 2)
    torch.save(data, tiny_checkpoint)
    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m")])
    assert_usage_error(result, str(tiny_checkpoint), "of another shape", "[2, 2]")


def test_export_rejects_an_out_it_cannot_make_and_a_bad_accuracy_json(tmp_path, tiny_checkpoint) -> None:
    (tmp_path / "a_file").write_text("x")
    for out, problem in ((tmp_path / "a_file", "a file, not a model folder"),
                         (tmp_path / "a_file" / "m", "is not a folder")):
        result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(out)])
        assert_usage_error(result, "--out", str(out), problem)
    for kind, problem in (("missing", "no such file"), ("random", "not a JSON file")):
        path = bad_file(tmp_path, kind)
        result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m"),
                                     "--accuracy-json", str(path)])
        assert_usage_error(result, "--accuracy-json", str(path), problem)


def test_export_rejects_a_data_folder_without_the_parity_shapes(tmp_path, tiny_checkpoint, monkeypatch) -> None:
    monkeypatch.setenv("MFGNET_DATA", str(tmp_path / "none"))
    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m")])
    assert_usage_error(result, str(tmp_path / "none"), "folder not found")


@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_A_CHECKPOINT])
def test_import_checkpoint_rejects_a_file_that_is_not_a_checkpoint(tmp_path, kind) -> None:
    path = bad_file(tmp_path, kind)
    result = runner.invoke(app, ["import-checkpoint", str(path), "--out", str(tmp_path / "o.pt")])
    assert_usage_error(result, "SOURCE", str(path), {**NOT_A_FILE, **NOT_A_CHECKPOINT}[kind])


def test_import_checkpoint_rejects_a_project_checkpoint_and_wrong_tensors(tmp_path, tiny_checkpoint) -> None:
    result = runner.invoke(app, ["import-checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "o.pt")])
    assert_usage_error(result, str(tiny_checkpoint), "not an authors' released checkpoint")
    wrong = tmp_path / "wrong.t7"
    torch.save({f"t{i}": torch.zeros(1) for i in range(215)}, wrong)  # the right count, none of the keys
    result = runner.invoke(app, ["import-checkpoint", str(wrong), "--out", str(tmp_path / "o.pt")])
    assert_usage_error(result, str(wrong), "not an authors' released checkpoint")
    assert not (tmp_path / "o.pt").exists()


def test_import_checkpoint_rejects_an_out_it_cannot_write(tmp_path, tiny_checkpoint) -> None:
    (tmp_path / "a_file").write_text("x")
    for out, problem in ((tmp_path, "a folder, not a file"), (tmp_path / "a_file" / "o.pt", "is not a folder")):
        result = runner.invoke(app, ["import-checkpoint", str(tiny_checkpoint), "--out", str(out)])
        assert_usage_error(result, "--out", str(out), problem)
