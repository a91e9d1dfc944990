"""``mfgnet export`` and ``mfgnet import-checkpoint`` on bad files: a one-line usage error (exit 2), no traceback;
an export that fails leaves its ``--out`` as it was."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from bad_files import NOT_A_CHECKPOINT, NOT_A_FILE, assert_usage_error, bad_file
from pair_checks import needs_modelnet
from shapes import sphere_shapes
from tiny_training import tiny_training_data
from typer.testing import CliRunner

from service.cli import app
from service.manifest import bundled_models_dir

runner = CliRunner()


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
    assert_usage_error(result, str(tiny_checkpoint), "already a checkpoint of this project", "directly with "
                       "--checkpoint")
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


def tiny_modelnet(tmp_path, monkeypatch, shapes: int = 3) -> None:
    """``$MFGNET_DATA``: a few spheres as the train and test splits (the reference radius, the parity pairs)."""
    folder = tmp_path / "data"
    folder.mkdir()
    for split in ("train", "test"):
        np.savez(folder / f"modelnet40_{split}.npz", points=sphere_shapes(shapes, seed=1), labels=np.arange(shapes))
    monkeypatch.setenv("MFGNET_DATA", str(folder))


@pytest.fixture
def diverging_checkpoint(tiny_checkpoint):
    """The tiny checkpoint with one layer's weights times 1e30: its ONNX graphs and PyTorch part ways, so the real
    parity check fails."""
    data = torch.load(tiny_checkpoint, weights_only=False)
    data["model"]["encoder.blocks.0.edge.linear.weight"] *= 1e30
    torch.save(data, tiny_checkpoint)
    return tiny_checkpoint


def export_args(checkpoint, out, pairs: int = 2) -> list[str]:
    """An export on ``pairs`` parity pairs that needs all of them comparable (fewer than the default minimum)."""
    return ["export", "--checkpoint", str(checkpoint), "--out", str(out), "--parity-pairs", str(pairs),
            "--min-comparable", str(pairs)]


def folder_contents(folder) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in folder.iterdir()}


def bundled_copy(folder):
    """A copy of the bundled model folder ``clean`` at ``folder``: an existing model folder to export into."""
    shutil.copytree(bundled_models_dir() / "clean", folder)
    return folder


def test_a_failed_export_leaves_an_existing_model_folder_and_its_other_files_as_they_were(
        tmp_path, diverging_checkpoint, monkeypatch) -> None:
    tiny_modelnet(tmp_path, monkeypatch)
    out = bundled_copy(tmp_path / "models" / "clean")
    (out / "notes.txt").write_text("not the exporter's")
    before = folder_contents(out)
    result = runner.invoke(app, export_args(diverging_checkpoint, out))
    assert out.is_dir() and folder_contents(out) == before  # the unrelated file, the graphs, the manifest: untouched
    assert result.exit_code == 1 and "ONNX parity failed" in result.stderr and "left as it was" in result.stderr
    assert sorted(path.name for path in out.parent.iterdir()) == ["clean"]  # no staging folder left


def test_a_failed_or_interrupted_export_to_a_new_folder_leaves_nothing(
        tmp_path, diverging_checkpoint, monkeypatch) -> None:
    tiny_modelnet(tmp_path, monkeypatch)
    (tmp_path / "models").mkdir()
    result = runner.invoke(app, export_args(diverging_checkpoint, tmp_path / "models" / "new" / "m"))
    assert result.exit_code == 1 and "ONNX parity failed" in result.stderr
    assert list((tmp_path / "models").iterdir()) == []  # neither the model nor the folder made for it

    def interrupted(*args, **kwargs):  # Ctrl-C while the graphs are written
        raise KeyboardInterrupt

    monkeypatch.setattr("export.onnx_export.reference_radius", interrupted)
    (tmp_path / "models" / "empty").mkdir()
    result = runner.invoke(app, export_args(diverging_checkpoint, tmp_path / "models" / "empty"))
    assert result.exit_code != 0
    assert [path.name for path in (tmp_path / "models").iterdir()] == ["empty"]
    assert list((tmp_path / "models" / "empty").iterdir()) == []


DESCRIPTION = "clean, fine-tuned on scans"


def clean_export_args(out) -> list[str]:
    """A real export of the bundled ``clean``: parity on one seeded pair (seed 0: comparable, as it then needs; each
    pair costs ~1 s, and parity is not what the tests using it check)."""
    return [*export_args("clean", out, pairs=1), "--seed", "0"]


# A real export of `clean` takes 3-7 s (graphs, reference radius, parity): the re-export and description tests share
# two, each into a folder of its own that no test changes afterwards.
@pytest.fixture(scope="module")
def described_clean(tmp_path_factory):
    """``clean`` exported with ``--description`` to a new folder ``clean_v2``: the command's result, the folder."""
    out = tmp_path_factory.mktemp("described") / "clean_v2"
    return runner.invoke(app, [*clean_export_args(out), "--description", DESCRIPTION]), out


@pytest.fixture(scope="module")
def re_exported_clean(tmp_path_factory, described_clean):
    """``clean`` exported again, with ``--version 9.9.9`` and no ``--description``, into a copy of
    ``described_clean``'s model folder holding a file of its own (notes.txt): the command's result, the folder, and
    the folder's file names before."""
    described, folder = described_clean
    assert described.exit_code == 0, described.output
    out = tmp_path_factory.mktemp("re_export") / "clean_v2"
    shutil.copytree(folder, out)
    (out / "notes.txt").write_text("not the exporter's")
    before = sorted(path.name for path in out.iterdir())
    return runner.invoke(app, [*clean_export_args(out), "--version", "9.9.9"]), out, before


@needs_modelnet
def test_a_re_export_replaces_the_graphs_and_manifest_and_keeps_the_folders_other_files(re_exported_clean) -> None:
    """The bundled checkpoint ``clean`` exported again into a model folder it was exported to before, with the real
    parity check."""
    from export.parity import EMBEDDING_SPREAD_MIN
    from service.manifest import load_manifest

    result, out, graphs = re_exported_clean
    assert result.exit_code == 0, result.output
    assert load_manifest(out).version == "9.9.9"
    assert "Likely cause" not in result.output
    spread = json.loads((out / "manifest.json").read_text())["parity"]["embedding_spread"]
    assert spread > 10 * EMBEDDING_SPREAD_MIN  # a trained network's embeddings: far from the untrained signature
    assert (out / "notes.txt").read_text() == "not the exporter's"
    assert sorted(path.name for path in out.iterdir()) == graphs
    assert [path.name for path in out.parent.iterdir()] == ["clean_v2"]  # no staging folder left


def test_export_of_a_barely_trained_network_fails_parity_and_says_why_and_what_to_do(tmp_path, monkeypatch) -> None:
    """The README's smoke run, smaller (one batch of 2 sphere pairs), then its export: parity fails (exit 1) as it
    must, and the message names the untrained network's nearly identical embeddings and what to do instead."""
    (tmp_path / "train").mkdir()
    run = tmp_path / "run"
    trained = runner.invoke(app, ["train", "--setting", "resampled", "--recipe", "general", "--out", str(run),
                                  "--epochs", "1", "--batches-per-epoch", "1", "--batch-size", "2", "--val-pairs", "2",
                                  "--data", tiny_training_data(tmp_path / "train"), "--threads", "1"])
    assert trained.exit_code == 0, trained.output
    tiny_modelnet(tmp_path, monkeypatch)
    out = tmp_path / "smoke"
    result = runner.invoke(app, export_args(run / "best.pt", out))
    assert result.exit_code == 1, result.output
    message = " ".join(result.stderr.split())
    assert "ONNX parity failed: matcher differs by" in message  # the failure itself, as before
    assert "Likely cause: the keypoint embeddings are nearly identical" in message
    assert "untrained or barely trained network" in message and "cancels to float32 rounding" in message
    assert "What to do: train longer (this checkpoint records 1 epoch, validation MAE(R)" in message
    assert "bundled checkpoints (clean, noise, unseen, general) export cleanly" in message
    assert f"mfgnet evaluate --checkpoint {run / 'best.pt'}" in message
    assert "more --parity-pairs give more comparable ones" not in message  # they would not: the scores tie
    assert not out.exists()


def test_export_refuses_a_folder_of_other_files_and_an_out_that_is_no_model_name(tmp_path, tiny_checkpoint) -> None:
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "notes.txt").write_text("x")
    result = runner.invoke(app, export_args(tiny_checkpoint, tmp_path / "m"))
    assert_usage_error(result, "--out", str(tmp_path / "m"), "not a model folder")
    assert [path.name for path in (tmp_path / "m").iterdir()] == ["notes.txt"]
    result = runner.invoke(app, export_args(tiny_checkpoint, tmp_path / "My Model"))
    assert_usage_error(result, "--out", "'My Model'", "no model name")


def parity_with_ties(monkeypatch, comparable_share: float = 0.54) -> list[int]:
    """``check_parity`` as the bundled ``clean`` passes it: the graphs agree, ``comparable_share`` of the pairs are
    comparable and the others excluded as ties; returns the ``min_compared`` it was called with."""
    from export.parity import ParityError, ParityReport

    seen = []

    def check_parity(model, registrar, pairs, min_compared):
        seen.append(min_compared)
        count = len(pairs["source"])
        compared = round(comparable_share * count)
        if compared < min_compared:
            raise ParityError(f"ONNX parity failed: only {compared} comparable pairs (< {min_compared})")
        return ParityReport(count, compared, count - compared, 0, 0, 1e-6, 1e-6, 1e-5, 1e-7)

    monkeypatch.setattr("export.parity.check_parity", check_parity)
    return seen


def test_export_passes_parity_when_half_the_pairs_are_ties(tmp_path, tiny_checkpoint, monkeypatch) -> None:
    """50 parity pairs, 27 comparable (the bundled clean's share): enough; parity does not need every pair."""
    from export import MIN_COMPARED

    tiny_modelnet(tmp_path, monkeypatch, shapes=50)
    seen = parity_with_ties(monkeypatch)
    out = tmp_path / "m"
    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(out),
                                 "--parity-pairs", "50"])
    assert result.exit_code == 0, result.output
    assert seen == [MIN_COMPARED]
    parity = json.loads((out / "manifest.json").read_text())["parity"]
    assert (parity["pairs"], parity["compared"], parity["excluded_ties"]) == (50, 27, 23)


def test_export_refuses_fewer_parity_pairs_than_comparable_pairs_it_needs(tmp_path, tiny_checkpoint) -> None:
    from export import MIN_COMPARED

    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m"),
                                 "--parity-pairs", str(MIN_COMPARED - 1)])
    assert_usage_error(result, f"--min-comparable {MIN_COMPARED}", f"{MIN_COMPARED - 1} --parity-pairs")
    assert not (tmp_path / "m").exists()


def evaluate_json(path, **evaluated) -> object:
    """An ``mfgnet evaluate --json`` output on 300 seeded noise pairs, with ``evaluated`` (what was measured: the
    checkpoint's hash, say); without, as evaluate wrote it before it recorded that."""
    metrics = {"n": 300, "rmse_r": 1.5, "mae_r": 0.7}
    if evaluated:
        metrics["evaluated"] = {"pairs": {"setting": "noise", "split": "test", "count": 300, "seed": 0}, **evaluated}
    path.write_text(json.dumps(metrics))
    return path


def test_export_carries_what_the_accuracy_was_measured_on_into_the_manifest(tmp_path, tiny_checkpoint,
                                                                            monkeypatch) -> None:
    from model.checkpoint import file_sha256

    tiny_modelnet(tmp_path, monkeypatch)
    parity_with_ties(monkeypatch, comparable_share=1.0)
    accuracy = evaluate_json(tmp_path / "noise_300.json", checkpoint="tiny.pt",
                             checkpoint_sha256=file_sha256(tiny_checkpoint), iterations=4)
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m"), "--accuracy-json", str(accuracy)])
    assert result.exit_code == 0, result.output
    section = json.loads((tmp_path / "m" / "manifest.json").read_text())["accuracy"]
    assert section["metrics"] == {"n": 300, "rmse_r": 1.5, "mae_r": 0.7} and section["on"] == "noise_300.json"
    assert section["evaluated"]["pairs"] == {"setting": "noise", "split": "test", "count": 300, "seed": 0}
    assert section["evaluated"]["checkpoint"] == "tiny.pt" and section["evaluated"]["iterations"] == 4

    older = evaluate_json(tmp_path / "older.json")
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m2"), "--accuracy-json", str(older)])
    assert result.exit_code == 0, result.output
    section = json.loads((tmp_path / "m2" / "manifest.json").read_text())["accuracy"]
    assert section == {"metrics": {"n": 300, "rmse_r": 1.5, "mae_r": 0.7}, "on": "older.json"}


def test_export_carries_the_checkpoints_training_provenance_into_the_manifest(tmp_path, tiny_checkpoint,
                                                                             monkeypatch) -> None:
    """``training``: what ``mfgnet train`` recorded in the checkpoint; a manifest without it (a checkpoint that
    records none) loads as before."""
    from service.manifest import load_manifest

    tiny_modelnet(tmp_path, monkeypatch)
    parity_with_ties(monkeypatch, comparable_share=1.0)
    result = runner.invoke(app, export_args(tiny_checkpoint, tmp_path / "plain"))
    assert result.exit_code == 0, result.output
    assert "training" not in json.loads((tmp_path / "plain" / "manifest.json").read_text())
    made_by = {"run": {"commit": "a" * 40, "uncommitted_changes": False, "command": ["mfgnet", "train"],
                       "data": {"folder": "/data", "file": "modelnet40_train.npz", "bytes": 5, "sha256": "b" * 64}},
               "resumes": [{"commit": None, "uncommitted_changes": None, "at": {"epoch": 3, "batch": 0}}]}
    data = torch.load(tiny_checkpoint, weights_only=True)
    torch.save({**data, "provenance": made_by}, tiny_checkpoint)
    result = runner.invoke(app, export_args(tiny_checkpoint, tmp_path / "trained"))
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "trained" / "manifest.json").read_text())["training"] == made_by
    for name in ("plain", "trained"):
        assert load_manifest(tmp_path / name).name == name


def test_export_reads_its_shapes_from_data_and_refuses_shapes_with_nan_points(tmp_path, tiny_checkpoint,
                                                                              monkeypatch) -> None:
    """``--data`` (as train, evaluate and make-pairs take it; export had only ``$MFGNET_DATA``, yet its error said
    "set --data"): the reference radius' and the parity pairs' shapes; a shape with a NaN point there is a usage
    error."""
    tiny_modelnet(tmp_path, monkeypatch)
    parity_with_ties(monkeypatch, comparable_share=1.0)
    data = str(tmp_path / "data")
    monkeypatch.setenv("MFGNET_DATA", str(tmp_path / "nowhere"))
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m"), "--data", data])
    assert result.exit_code == 0, result.output
    points = sphere_shapes(3, seed=1)
    points[2, 0, 0] = np.nan
    np.savez(tmp_path / "data" / "modelnet40_train.npz", points=points, labels=np.arange(3))
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m2"), "--data", data])
    assert_usage_error(result, f"{data}/modelnet40_train.npz", "NaN or infinite", "index 2")
    assert not (tmp_path / "m2").exists()


@pytest.mark.parametrize(("evaluated", "problem"), [
    ({"checkpoint_sha256": "0" * 64}, "another checkpoint (sha256 000000000000"),
    ({"baseline": "fpfh-ransac-icp"}, "baseline fpfh-ransac-icp"),
    ({"model": "old", "checkpoint_sha256": None}, "a model that does not record its checkpoint"),
])
def test_export_refuses_an_accuracy_measured_on_something_else(tmp_path, tiny_checkpoint, evaluated, problem) -> None:
    path = evaluate_json(tmp_path / "a.json", **evaluated)
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m"), "--accuracy-json", str(path)])
    assert_usage_error(result, f"--accuracy-json {path}", problem, f"not with --checkpoint {tiny_checkpoint}")
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize(("setting", "problem"), [("bogus", "unknown setting"), ("dense", "a test-only setting"),
                                                  ("scans", "a test-only setting")])
def test_export_rejects_a_setting_without_training_shapes(tmp_path, tiny_checkpoint, setting, problem) -> None:
    """The reference radius is measured on the setting's training shapes: a setting without any is a usage error
    before anything is exported, not a traceback after the graphs were written."""
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m"), "--setting", setting])
    assert_usage_error(result, f"--setting {setting}", problem, "clean, noise, unseen, resampled")
    assert not (tmp_path / "m").exists()


@needs_modelnet
def test_export_measures_the_reference_radius_on_the_setting_the_checkpoint_was_trained_on(tmp_path) -> None:
    """The bundled ``unseen`` checkpoint exported without --setting gets the bundled ``unseen`` model's reference
    radius (its training shapes are categories 0-19 only), not ``clean``'s (real parity on one seeded pair, which is
    comparable: parity is not what this checks, and each pair costs ~1 s)."""
    out = tmp_path / "unseen"
    result = runner.invoke(app, ["export", "--checkpoint", "unseen", "--out", str(out), "--parity-pairs", "1",
                                 "--min-comparable", "1", "--seed", "5"])
    assert result.exit_code == 0, result.output
    radius = json.loads((out / "manifest.json").read_text())["normalization"]["reference_radius"]
    bundled = {name: json.loads((bundled_models_dir() / name / "manifest.json").read_text())["normalization"]
               ["reference_radius"] for name in ("unseen", "clean")}
    assert radius == pytest.approx(bundled["unseen"], rel=1e-9) and radius != pytest.approx(bundled["clean"], rel=1e-3)


OFFICIAL = Path(__file__).resolve().parents[3] / "shared" / "weights" / "official" / "model_clean.t7"


def test_export_names_import_checkpoint_for_bare_weights(tmp_path, tiny_checkpoint) -> None:
    """A state_dict without this project's config (as the authors' ``model_*.t7`` are) is a usage error that names
    the command converting it."""
    bare = tmp_path / "bare.t7"
    torch.save(torch.load(tiny_checkpoint, weights_only=True)["model"], bare)
    result = runner.invoke(app, export_args(bare, tmp_path / "m"))
    assert_usage_error(result, f"--checkpoint {bare}", "bare weights", f"mfgnet import-checkpoint {bare}")
    assert not (tmp_path / "m").exists()


@pytest.mark.skipif(not OFFICIAL.is_file(), reason=f"the authors' released weights are not at {OFFICIAL}")
def test_the_authors_checkpoint_is_refused_by_export_and_imported_by_import_checkpoint(tmp_path) -> None:
    result = runner.invoke(app, export_args(OFFICIAL, tmp_path / "m"))
    assert_usage_error(result, "bare weights", f"mfgnet import-checkpoint {OFFICIAL}")
    imported = tmp_path / "official_clean.pt"
    result = runner.invoke(app, ["import-checkpoint", str(OFFICIAL), "--out", str(imported)])
    assert result.exit_code == 0, result.output
    assert "(3 iterations, K = 256)" in result.stdout
    from model.cli_inputs import checkpoint_model

    _, data, model = checkpoint_model(imported)
    assert data["source"] == OFFICIAL.name and (model.cfg.iterations, model.cfg.keypoints) == (3, 256)


@needs_modelnet
def test_export_writes_the_description_that_mfgnet_models_shows_and_a_re_export_keeps_it(
        described_clean, re_exported_clean) -> None:
    """``--description`` is the manifest's ``description``, the FOR column of ``mfgnet models`` (real exports of the
    bundled ``clean``: to a new folder with it, then into that folder again without it)."""
    for result, out in (described_clean, re_exported_clean[:2]):  # exported, then re-exported without it
        assert result.exit_code == 0, result.output
        listed = runner.invoke(app, ["models", "--json", "--model-dir", str(out)])
        entry = next(e for e in json.loads(listed.stdout) if e["name"] == "clean_v2")
        assert entry["purpose"] == DESCRIPTION
        assert DESCRIPTION in runner.invoke(app, ["models", "--model-dir", str(out)]).stdout


@pytest.mark.parametrize("description", ["", "two\nlines", "x" * 61])
def test_export_rejects_a_description_that_is_not_one_short_line(tmp_path, tiny_checkpoint, description) -> None:
    result = runner.invoke(app, [*export_args(tiny_checkpoint, tmp_path / "m"), "--description", description])
    assert_usage_error(result, "--description", "one line of 1 to 60 printable characters")
    assert not (tmp_path / "m").exists()


def test_import_checkpoint_does_not_replace_an_existing_out(tmp_path, tiny_checkpoint) -> None:
    """It replaced the file without a word (a training run's checkpoint among them); export and train refuse."""
    out = tmp_path / "mine.pt"
    shutil.copy(tiny_checkpoint, out)
    before = out.read_bytes()
    result = runner.invoke(app, ["import-checkpoint", str(tmp_path / "any.t7"), "--out", str(out)])
    assert_usage_error(result, "--out", str(out), "already exists")
    assert out.read_bytes() == before


@pytest.mark.parametrize("version", ["", " 1.0", "1.0\nnext", "v" * 65])
def test_export_refuses_a_version_that_is_no_table_cell(tmp_path, tiny_checkpoint, version) -> None:
    """An empty version or one holding a line break went into the manifest and broke `mfgnet models`' table."""
    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m"),
                                 "--version", version])
    assert_usage_error(result, "--version", "up to 64 letters, digits")
    assert not (tmp_path / "m").exists()


def test_parity_on_a_test_split_of_fewer_shapes_says_so(tmp_path, tiny_checkpoint, monkeypatch) -> None:
    """A dataset of 3 test shapes: --parity-pairs 100 was cut to 3 without a word (and a failure for too few comparable
    pairs said only "more pairs give more comparable ones", which the split cannot; it names --min-comparable now)."""
    tiny_modelnet(tmp_path, monkeypatch)
    result = runner.invoke(app, ["export", "--checkpoint", str(tiny_checkpoint), "--out", str(tmp_path / "m"),
                                 "--parity-pairs", "10", "--min-comparable", "5"])
    message = " ".join(result.stderr.split())
    assert "note: the test split holds 3 shapes: parity on as many pairs, not --parity-pairs 10" in message
    assert result.exit_code == 1  # an untrained network: its parity fails for its own reason


def test_an_export_whose_config_the_runtime_refuses_fails_and_says_so(tmp_path, tiny_checkpoint, monkeypatch) -> None:
    """A checkpoint whose config asks for 100,000 keypoints: the model folder's check refused it with a traceback
    (before that check, the exported model refused every request naming no keypoints)."""
    tiny_modelnet(tmp_path, monkeypatch)
    data = torch.load(tiny_checkpoint, weights_only=False)
    data["config"]["keypoints"] = 100_000
    torch.save(data, tiny_checkpoint)
    out = tmp_path / "m"
    result = runner.invoke(app, export_args(tiny_checkpoint, out))
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert f"export failed, {out} left as it was" in result.stderr and "keypoints 100000" in result.stderr
    assert not out.exists()
