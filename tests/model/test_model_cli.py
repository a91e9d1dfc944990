"""The training-side ``mfgnet`` sub-commands (train, make-pairs) through the one ``mfgnet`` app."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tiny_training import save_tiny_checkpoint
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


@pytest.fixture
def tiny_checkpoint(tmp_path):
    path = tmp_path / "tiny.pt"
    save_tiny_checkpoint(path)
    return path


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
    assert set(metrics) == METRIC_KEYS
    assert metrics["n"] == 4
