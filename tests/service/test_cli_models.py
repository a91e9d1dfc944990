"""Specification of ``mfgnet models``: bundled and --model-dir models with their manifest figures, and
models that fail verification listed with the reason."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_support import snapshot_model
from typer.testing import CliRunner

from service.cli import app
from service.manifest import bundled_models_dir, load_manifest

runner = CliRunner()


@pytest.fixture(scope="module")
def models_root(tmp_path_factory) -> Path:
    """A folder of model folders: a verified ``clean`` and a ``bare`` one with a graph but no manifest."""
    root = tmp_path_factory.mktemp("models")
    snapshot_model(root)
    (root / "bare").mkdir()
    (root / "bare" / "encoder.onnx").write_bytes(b"\0")
    return root


@pytest.fixture(scope="module")
def tampered_model(tmp_path_factory, models_root) -> Path:
    """A copy of ``clean`` whose ``matcher_2.onnx`` no longer matches the manifest."""
    tampered = tmp_path_factory.mktemp("tampered") / "clean"
    shutil.copytree(models_root / "clean", tampered)
    (tampered / "matcher_2.onnx").write_bytes(b"tampered")
    return tampered


def list_models(*args) -> tuple[int, object, str]:
    return invoke("models", *args)


def invoke(*args) -> tuple[int, object, str]:
    result = runner.invoke(app, [*map(str, args)])
    return result.exit_code, result.stdout, result.stderr


def test_bundled_models_are_listed_as_json() -> None:
    if not (bundled_models_dir() / "clean" / "manifest.json").exists():
        pytest.skip("the bundled model 'clean' is not exported yet")
    code, out, _ = list_models("--json")
    assert code == 0
    entries = json.loads(out)
    clean = next(e for e in entries if e["name"] == "clean")
    assert clean["status"] == "ok" and Path(clean["directory"]) == bundled_models_dir() / "clean"


def test_json_gives_name_version_iterations_keypoints_accuracy_and_hash(models_root) -> None:
    code, out, _ = list_models("--json", "--model-dir", models_root)
    assert code == 0
    entries = json.loads(out)
    clean = next(e for e in entries if e["directory"] == str(models_root / "clean"))
    manifest = json.loads((models_root / "clean" / "manifest.json").read_text())
    assert clean["status"] == "ok"
    assert clean["name"] == "clean" and clean["version"] == manifest["version"]
    assert clean["iterations"] == manifest["config"]["iterations"]
    assert clean["keypoints"] == manifest["config"]["keypoints"]
    assert clean["accuracy"] == manifest["accuracy"] and len(clean["sha256"]) == 64


def test_models_failing_verification_are_listed_with_the_reason(models_root, tampered_model) -> None:
    code, out, _ = list_models("--json", "--model-dir", models_root, "--model-dir", tampered_model)
    assert code == 0  # the verified models are still usable
    failed = {e["directory"]: e for e in json.loads(out) if e["status"] == "failed"}
    assert "manifest.json is missing" in failed[str(models_root / "bare")]["error"]
    assert "sha256 of matcher_2.onnx does not match" in failed[str(tampered_model)]["error"]


def test_table_shows_name_version_purpose_and_the_failures(models_root) -> None:
    code, out, _ = list_models("--model-dir", models_root)
    assert code == 0
    header, *rows = out.splitlines()
    assert header.split() == ["NAME", "VERSION", "ITER", "K", "GRAPHS", "FOR", "WHERE"]
    clean = next(row for row in rows if row.endswith("/clean"))  # the folder's tail (elided to fit 100 columns)
    assert clean.split()[:2] == ["clean", load_manifest(models_root / "clean").version]
    assert "paper protocol" in clean and all(len(row) <= 100 for row in rows)
    assert any(row.startswith("FAILED bare:") and "manifest.json is missing" in row for row in rows)


def test_table_shows_no_manifest_figures_and_json_keeps_them(tmp_path, models_root) -> None:
    """Each manifest's figures are on that model's own validation pairs: not comparable, so not in the table."""
    model = tmp_path / "clean"
    shutil.copytree(models_root / "clean", model)
    manifest = json.loads((model / "manifest.json").read_text())
    manifest["accuracy"] = {"metrics": {"rmse_r": 1.25, "mae_r": 0.5, "n": 100}, "on": "val pairs"}
    (model / "manifest.json").write_text(json.dumps(manifest))  # graphs are hashed, the manifest is not
    code, out, _ = list_models("--model-dir", model)
    assert code == 0 and "rmse_r" not in out and "1.25" not in out and "val pairs" not in out
    code, out, _ = list_models("--model-dir", model, "--json")
    entry = next(e for e in json.loads(out) if e["directory"] == str(model))
    assert entry["accuracy"]["metrics"]["rmse_r"] == 1.25 and entry["default"] is True  # the only --model-dir one


def test_exit_code_1_when_no_model_is_usable(tmp_path, monkeypatch) -> None:
    import service.manifest

    monkeypatch.setattr(service.manifest, "bundled_models_dir", lambda: tmp_path / "none")
    (tmp_path / "bare").mkdir()
    (tmp_path / "bare" / "encoder.onnx").write_bytes(b"\0")
    code, out, _ = list_models("--model-dir", tmp_path)
    assert code == 1 and out.startswith("FAILED bare:")
    code, out, _ = list_models()
    assert code == 1 and "no models found" in out


def test_a_model_dir_that_is_not_a_folder_or_holds_no_model_is_a_usage_error(tmp_path) -> None:
    """It was ignored: the bundled models were listed (or used) as if it had not been given, as `mfgnet serve` refuses
    it."""
    (tmp_path / "empty" / "sub").mkdir(parents=True)
    clouds = [tmp_path / "a.npy", tmp_path / "b.npy"]
    for path in clouds:
        np.save(path, np.random.default_rng(0).normal(size=(64, 3)).astype(np.float32))
    for command in (["models"], ["register", *clouds], ["sequence", *clouds]):
        code, _, err = invoke(*command, "--model-dir", tmp_path / "nonexistent")
        assert code == 2 and "not a folder" in err, command
        code, _, err = invoke(*command, "--model-dir", tmp_path / "empty")
        assert code == 2 and f"--model-dir {tmp_path / 'empty'}: no model in it" in err, command


def test_a_failed_default_is_named_below_the_table(tmp_path) -> None:
    """The only --model-dir model is the default even when it fails: `mfgnet register` stopped on it, while the table
    marked no default. A missing manifest field is named as one (it printed "('name')")."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "manifest.json").write_text("{}")
    code, out, _ = list_models("--model-dir", tmp_path / "mine")
    assert code == 0 and "FAILED mine: model 'mine': malformed manifest.json (no 'name' field)" in out
    assert "the default, mine, failed: `mfgnet register` without --model stops on it" in out


def test_a_model_named_like_a_bundled_one_is_not_given_its_purpose(tmp_path, models_root) -> None:
    """A user's model exported under a bundled model's name (its manifest differs) is described by its own manifest
    only: it was listed as the bundled model's purpose. A copy of the bundled model keeps it."""
    own = tmp_path / "clean"
    shutil.copytree(models_root / "clean", own)
    manifest = json.loads((own / "manifest.json").read_text())
    manifest["version"] = "9.9.9"
    (own / "manifest.json").write_text(json.dumps(manifest))
    code, out, _ = list_models("--json", "--model-dir", own, "--model-dir", models_root)
    entries = {e["directory"]: e for e in json.loads(out)}
    assert code == 0 and entries[str(own)]["status"] == "ok"
    assert entries[str(own)]["purpose"] is None
    assert entries[str(models_root / "clean")]["purpose"] == "paper protocol: shared points, clean"
