"""``scripts/device_train.py``: the seeded data subset and the two time-limited phases (on CPU)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
from shapes import sphere_shapes

from model.checkpoint import save_checkpoint
from model.config import MFGNetConfig
from model.network import MFGNet

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "device_train.py"


def script(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], cwd=ROOT, env={**os.environ, **env},
                          capture_output=True, text=True, timeout=300, check=True)


def training_file(folder: Path, seed: int) -> np.ndarray:
    """A small ``modelnet40_train.npz`` of 48 seeded shapes in ``folder``; returns its labels."""
    folder.mkdir()
    labels = np.arange(48) % 40
    np.savez(folder / "modelnet40_train.npz", points=sphere_shapes(48, seed=seed).astype(np.float16), labels=labels)
    return labels


def test_subset_and_both_phases_leave_the_files_that_come_back(tmp_path) -> None:
    data = tmp_path / "data"
    labels = training_file(data, seed=2)
    subset = tmp_path / "subset"
    script("subset", "--out", str(subset), "--shapes", "30", "--seed", "1", env={"MFGNET_DATA": str(data)})
    with np.load(subset / "modelnet40_train.npz") as written:
        keep = np.sort(np.random.default_rng(1).permutation(48)[:30])
        assert np.array_equal(written["labels"], labels[keep])
        assert written["points"].shape == (30, 1024, 3) and written["points"].dtype == np.float16

    out = tmp_path / "out"
    init = tmp_path / "init.pt"
    torch.manual_seed(0)
    save_checkpoint(init, MFGNet(MFGNetConfig()))
    run = script("run", "--data", str(subset), "--init", str(init), "--minutes-a", "0.01", "--minutes-b", "0.01",
                 "--device", "cpu", "--batch-size", "2", "--views-share", "1.0", env={"OUT": str(out)})
    assert "all done" in run.stdout
    assert not (out / "a" / "last.pt").exists() and not (out / "a" / "config.json").exists()  # handed to phase b
    assert (out / "b" / "last.pt").exists() and not (out / "b" / "config.json").exists()
    files = [p for p in out.rglob("*") if p.is_file()]
    assert len(files) <= 8  # what a device run can bring back


def load_script():
    """``scripts/device_train.py`` as a module, to run its ``main`` in this process (``model.train`` patched)."""
    spec = importlib.util.spec_from_file_location("device_train", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_failed_phase_is_retried_over_what_it_left_and_an_earlier_run_is_kept(tmp_path, monkeypatch) -> None:
    import model.train

    data = tmp_path / "data"
    training_file(data, seed=5)
    real_train, tries, failures = model.train.train, [], [1]

    def failing_once(opts):
        tries.append((Path(opts.out).name, opts.resume, opts.overwrite))
        if failures.pop() if failures else 0:  # the worker died after an epoch's record, before any checkpoint
            Path(opts.out).mkdir(parents=True, exist_ok=True)
            (Path(opts.out) / "log.jsonl").write_text('{"epoch": 0}\n')
            raise RuntimeError("DataLoader worker exited unexpectedly")
        return real_train(opts)

    monkeypatch.setattr(model.train, "train", failing_once)
    args = ["run", "--data", str(data), "--minutes-a", "0.01", "--minutes-b", "0.01", "--device", "cpu",
            "--batch-size", "2", "--config", '{"emb_dims": 16, "encoder_blocks": 2}']
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    out = tmp_path / "out"
    monkeypatch.setenv("OUT", str(out))
    load_script().main()
    # phase a, its retry: a new run over the log the failed try left (no last.pt to resume), then phase b
    assert tries == [("a", False, False), ("a", False, True), ("b", False, False)]
    log = out / "a" / "log.jsonl"
    assert not log.exists() or all("train_total" in json.loads(line) for line in log.read_text().splitlines())

    earlier = tmp_path / "earlier"  # a phase folder that holds a run from before: refused, not retried over
    (earlier / "a").mkdir(parents=True)
    (earlier / "a" / "log.jsonl").write_text('{"epoch": 7}\n')
    monkeypatch.setenv("OUT", str(earlier))
    tries.clear()
    with pytest.raises(FileExistsError, match="holds a run already"):
        load_script().main()
    assert tries == [("a", False, False)]
    assert (earlier / "a" / "log.jsonl").read_text() == '{"epoch": 7}\n'


@pytest.mark.slow  # two more tiny training runs of the GPU script: on demand (make test-all; decisions/0098)
def test_a_cheaper_network_for_real_scans_trains_from_scratch(tmp_path) -> None:
    data = tmp_path / "data"
    training_file(data, seed=3)
    out = tmp_path / "out"
    run = script("run", "--data", str(data), "--recipe", "real", "--config", '{"emb_dims": 16, "encoder_blocks": 2}',
                 "--lr-a", "1e-3", "--minutes-a", "0.01", "--minutes-b", "0.01", "--device", "cpu", "--batch-size", "2",
                 env={"OUT": str(out)})
    assert "all done" in run.stdout
    last = torch.load(out / "b" / "last.pt", map_location="cpu", weights_only=False)  # best.pt after a validation
    assert last["config"]["emb_dims"] == 16 and last["config"]["encoder_blocks"] == 2


@pytest.mark.slow  # two more tiny training runs of the GPU script: on demand (make test-all; decisions/0098)
def test_runs_side_by_side_each_come_back_as_one_archive(tmp_path) -> None:
    data = tmp_path / "data"
    training_file(data, seed=4)
    out = tmp_path / "out"
    common = (f"--data {data} --minutes-a 0.01 --minutes-b 0.01 --device cpu --batch-size 2 "
              '--config \'{"emb_dims": 16, "encoder_blocks": 2}\'')
    run = script("side-by-side", "--hard-seconds", "240", "--run", f"one:--recipe general {common}",
                 "--run", f"two:--recipe search {common}", env={"OUT": str(out)})
    assert "one: exit 0" in run.stdout and "two: exit 0" in run.stdout
    assert sorted(p.name for p in out.iterdir()) == ["one.tar", "two.tar"]
    for name in ("one", "two"):
        with tarfile.open(out / f"{name}.tar") as packed:
            names = set(packed.getnames())
        assert {"./b/last.pt", "./train.log"} <= names, names

    killed = script("side-by-side", "--hard-seconds", "1", "--run", f"slow:--recipe general {common}",
                    env={"OUT": str(tmp_path / "killed")})
    assert "slow: exit -9" in killed.stdout  # killed, and still packed
    assert (tmp_path / "killed" / "slow.tar").exists()
