"""What a training run records of what made it (``provenance``: the checkout's commit, the data file, the command
line, the options, the versions) in its checkpoints and ``config.json``, kept and added to by ``--resume``."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch
from provenance_check import assert_this_checkout
from tiny_training import TINY_MODEL, tiny_training_data
from typer.testing import CliRunner

from model.checkpoint import read_checkpoint
from model.provenance import checkout
from service.cli import app

runner = CliRunner()


def assert_run_record(record: dict, data: str, **options) -> None:
    """``record`` names this checkout's commit, the data file read (its folder by name only, as it lies outside the
    working directory; its size and hash), this process's command line, the run's ``options`` (those given) and the
    versions of torch and numpy."""
    assert_this_checkout(record)
    file = Path(data).resolve() / "modelnet40_train.npz"
    assert record["data"] == {
        "folder": file.parent.name,
        "file": file.name,
        "bytes": file.stat().st_size,
        "sha256": hashlib.sha256(file.read_bytes()).hexdigest(),
    }
    assert record["command"] == sys.argv
    assert {key: record["options"][key] for key in options} == options
    assert record["versions"]["torch"] == torch.__version__ and record["versions"]["numpy"] == np.__version__


def test_a_run_records_what_made_it_and_a_resume_keeps_that_and_adds_its_own(tmp_path) -> None:
    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    args = [
        "train",
        "--out",
        str(run),
        "--data",
        data,
        "--batch-size",
        "2",
        "--batches-per-epoch",
        "1",
        "--val-pairs",
        "2",
        "--iterations",
        "1",
        "--device",
        "cpu",
    ]
    result = runner.invoke(app, [*args, "--epochs", "1", "--seed", "3"])
    assert result.exit_code == 0, result.output
    made_by = read_checkpoint(run / "last.pt")["provenance"]
    assert made_by["resumes"] == []
    assert_run_record(made_by["run"], data, seed=3, epochs=1, init=None)
    assert made_by["run"]["init"] is None
    assert read_checkpoint(run / "best.pt")["provenance"] == made_by
    assert json.loads((run / "config.json").read_text())["provenance"] == made_by

    result = runner.invoke(app, [*args, "--resume", "--epochs", "2"])
    assert result.exit_code == 0, result.output
    resumed = read_checkpoint(run / "last.pt")["provenance"]
    assert resumed["run"] == made_by["run"]  # the start's record, as it was
    assert len(resumed["resumes"]) == 1
    assert_run_record(resumed["resumes"][0], data, seed=3, epochs=2)
    assert resumed["resumes"][0]["at"] == {"epoch": 1, "batch": 0}
    assert json.loads((run / "config.json").read_text())["provenance"] == resumed


def test_a_fine_tuned_run_records_the_checkpoint_it_started_from(tmp_path, tiny_checkpoint) -> None:
    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    result = runner.invoke(
        app,
        [
            "train",
            "--out",
            str(run),
            "--data",
            data,
            "--init",
            str(tiny_checkpoint),
            "--epochs",
            "1",
            "--batch-size",
            "2",
            "--batches-per-epoch",
            "1",
            "--val-pairs",
            "2",
            "--device",
            "cpu",
        ],
    )
    assert result.exit_code == 0, result.output
    init = read_checkpoint(run / "last.pt")["provenance"]["run"]["init"]
    assert init == {
        "checkpoint": tiny_checkpoint.name,  # outside the working directory: its name
        "sha256": hashlib.sha256(tiny_checkpoint.read_bytes()).hexdigest(),
        "provenance": None,
    }


def test_checkout_names_the_commit_of_a_checkouts_top_folder_only(tmp_path) -> None:
    """Not the commit of a checkout around it: packages installed in a virtual environment inside a checkout."""
    import subprocess

    assert checkout(tmp_path) == {"commit": None, "uncommitted_changes": None}
    (tmp_path / "inside").mkdir()
    (tmp_path / "a.txt").write_text("a")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(tmp_path)]
    for args in (["init", "-q"], ["add", "a.txt"], ["commit", "-q", "-m", "a"]):
        subprocess.run([*git, *args], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert checkout(tmp_path) == {"commit": head, "uncommitted_changes": False}
    (tmp_path / "a.txt").write_text("b")
    assert checkout(tmp_path) == {"commit": head, "uncommitted_changes": True}
    assert checkout(tmp_path / "inside") == {"commit": None, "uncommitted_changes": None}


def test_library_runs_record_the_same(tmp_path) -> None:
    from model.train import TrainOptions, train

    data = tiny_training_data(tmp_path)
    train(
        TrainOptions(
            out=str(tmp_path / "run"),
            data=data,
            epochs=1,
            batch_size=2,
            max_batches_per_epoch=1,
            val_pairs=2,
            device="cpu",
            config=dict(TINY_MODEL),
        )
    )
    assert_run_record(read_checkpoint(tmp_path / "run" / "last.pt")["provenance"]["run"], data, batch_size=2)


def test_a_resume_on_other_data_says_so_and_records_it(tmp_path, capsys) -> None:
    """The data folder is the resuming process's (a run moves between machines); other contents are noted."""
    from model.train import TrainOptions, train

    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    opts = {
        "out": str(run),
        "batch_size": 2,
        "max_batches_per_epoch": 1,
        "val_pairs": 1,
        "device": "cpu",
        "config": dict(TINY_MODEL),
    }
    train(TrainOptions(data=data, epochs=1, **opts))
    train(TrainOptions(data=data, epochs=2, resume=True, **opts))
    assert "other data" not in capsys.readouterr().err  # the same file: nothing to say
    other = tmp_path / "other"
    other.mkdir()
    points = np.load(Path(data) / "modelnet40_train.npz")["points"][:20]
    np.savez(other / "modelnet40_train.npz", points=points, labels=np.arange(20))
    train(TrainOptions(data=str(other), epochs=3, resume=True, **opts))
    err = capsys.readouterr().err
    assert f"note: resuming on other data than the run's so far: {other}/modelnet40_train.npz" in err
    assert "not data/modelnet40_train.npz" in err
    resumes = read_checkpoint(run / "last.pt")["provenance"]["resumes"]
    assert [r["data"]["folder"] for r in resumes] == ["data", "other"]


def test_the_record_holds_no_absolute_path_and_a_checkpoint_with_one_still_resumes(tmp_path, monkeypatch, capsys):
    """A data folder inside the working directory is recorded relative to it, one outside by its name only (an
    absolute path says where a user keeps files, and nothing on another machine); the sha256 identifies the file. A
    checkpoint that recorded the absolute folder (before this) resumes, and its folder is quoted as recorded."""
    from model.train import TrainOptions, train

    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    inside = Path(tiny_training_data(work))  # work/data
    outside = Path(tiny_training_data(tmp_path))  # tmp_path/data: beside the working directory
    opts = {"batch_size": 2, "max_batches_per_epoch": 1, "val_pairs": 1, "device": "cpu", "config": dict(TINY_MODEL)}
    train(TrainOptions(out="run", data="data", epochs=1, **opts))
    train(TrainOptions(out="abs", data=str(outside), epochs=1, **opts))
    train(TrainOptions(out="init", data=str(inside), epochs=1, init=str(work / "run" / "last.pt"), **opts))
    for run, folder in (("run", "data"), ("abs", "data"), ("init", "data")):
        record = read_checkpoint(work / run / "last.pt")["provenance"]["run"]
        assert record["data"]["folder"] == folder
        assert json.loads((work / run / "config.json").read_text())["provenance"]["run"]["data"] == record["data"]
    assert read_checkpoint(work / "init" / "last.pt")["provenance"]["run"]["init"]["checkpoint"] == "run/last.pt"
    for run in ("run", "abs", "init"):
        text = json.dumps(read_checkpoint(work / run / "last.pt")["provenance"]["run"]["data"])
        assert str(tmp_path) not in text
    capsys.readouterr()

    old = read_checkpoint(work / "abs" / "last.pt")  # as written before: the absolute folder
    old["provenance"]["run"]["data"]["folder"] = str(outside)
    torch.save(old, work / "abs" / "last.pt")
    points = np.load(outside / "modelnet40_train.npz")["points"][:20]
    np.savez(work / "data" / "modelnet40_train.npz", points=points, labels=np.arange(20))
    train(TrainOptions(out="abs", data="data", epochs=2, resume=True, **opts))
    err = capsys.readouterr().err
    assert "resuming on other data than the run's so far: data/modelnet40_train.npz" in err
    assert f"not {outside}/modelnet40_train.npz" in err
    made_by = read_checkpoint(work / "abs" / "last.pt")["provenance"]
    assert made_by["run"]["data"]["folder"] == str(outside)  # the old record kept as it was
    assert made_by["resumes"][0]["data"]["folder"] == "data"


def test_a_run_says_when_it_validates_on_fewer_pairs_than_asked(tmp_path, capsys) -> None:
    from model.train import TrainOptions, train

    train(
        TrainOptions(
            out=str(tmp_path / "run"),
            data=tiny_training_data(tmp_path),
            epochs=1,
            batch_size=2,
            max_batches_per_epoch=1,
            val_pairs=256,
            device="cpu",
            config=dict(TINY_MODEL),
        )
    )
    assert (
        "validating on 1 pairs, not 256 (val_pairs): one per held-out shape, 1 of the 30 training shapes "
        "(val_fraction 0.04)"
    ) in capsys.readouterr().out
