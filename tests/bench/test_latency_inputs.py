"""``mfgnet bench`` on bad files: a one-line usage error (exit 2) naming the option and the file, before any
measuring (and without a dataset: ``$MFGNET_DATA`` points nowhere, so a check that came too late would show)."""

from __future__ import annotations

import json

import pytest
from bad_files import NOT_A_CHECKPOINT, NOT_A_FILE, NOT_A_MODEL, assert_usage_error, bad_file, bad_model
from typer.testing import CliRunner

from service.cli import app
from service.manifest import bundled_models_dir

runner = CliRunner()

needs_bundled_clean = pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").is_file(),
                                         reason="no bundled 'clean' model")
QUICK = ["--repeats", "2", "--http-requests", "0", "--accuracy-count", "0", "--no-classical"]


@pytest.fixture(autouse=True)
def no_dataset(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MFGNET_DATA", str(tmp_path / "no_data"))


@pytest.mark.parametrize("kind", NOT_A_MODEL)
def test_bench_rejects_a_model_that_is_not_a_model_folder(tmp_path, kind) -> None:
    model = bad_model(tmp_path, kind)
    result = runner.invoke(app, ["bench", "--model", model, *QUICK])
    assert_usage_error(result, "--model", model, NOT_A_MODEL[kind])


@needs_bundled_clean
@pytest.mark.parametrize("kind", [*NOT_A_FILE, *NOT_A_CHECKPOINT])
def test_bench_rejects_a_checkpoint_that_is_not_a_checkpoint(tmp_path, kind) -> None:
    path = bad_file(tmp_path, kind)
    result = runner.invoke(app, ["bench", "--model", "clean", "--checkpoint", str(path), *QUICK])
    problem = "no checkpoint file" if kind == "missing" else {**NOT_A_FILE, **NOT_A_CHECKPOINT}[kind]
    assert_usage_error(result, "--checkpoint", str(path), problem)


@needs_bundled_clean
@pytest.mark.parametrize("kind", ["missing", "folder", "random", "list", "other-json"])
def test_bench_rejects_a_compare_file_that_is_not_a_bench_report(tmp_path, kind) -> None:
    path = bad_file(tmp_path, kind) if kind in ("missing", "folder", "random") else tmp_path / "other.json"
    if kind in ("list", "other-json"):
        path.write_text(json.dumps([1, 2] if kind == "list" else {"n": 3}))
    problem = {"missing": "no such file", "folder": "a folder, not a file", "random": "not a JSON file",
               "list": "not an mfgnet bench report (a JSON list)", "other-json": "no 'pipeline_768'"}[kind]
    result = runner.invoke(app, ["bench", "--compare", str(path), *QUICK])
    assert_usage_error(result, "--compare", str(path), problem)


def test_bench_rejects_a_json_output_under_a_file_and_a_missing_dataset(tmp_path) -> None:
    (tmp_path / "a_file").write_text("x")
    result = runner.invoke(app, ["bench", "--json", str(tmp_path / "a_file" / "b.json"), *QUICK])
    assert_usage_error(result, "--json", "a_file", "is not a folder")
    if (bundled_models_dir() / "clean" / "manifest.json").is_file():
        assert_usage_error(runner.invoke(app, ["bench", *QUICK]), str(tmp_path / "no_data"), "folder not found")
