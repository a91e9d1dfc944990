"""``mfgnet evaluate`` (``bench.evaluate``) on a checkpoint or a classical baseline, through the one ``mfgnet`` app."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapes import sphere_shapes
from tiny_training import save_tiny_checkpoint
from typer.testing import CliRunner

from model.data import PairProtocol, make_pairs, save_pairs
from service.cli import app

METRIC_KEYS = {"n", "rmse_r", "mae_r", "rmse_t", "mae_t", "iso_r_mean", "iso_r_median", "iso_t_mean",
               "iso_t_median", "recall_r1_t001", "recall_r5_t005", "ms_per_pair"}

runner = CliRunner()


@pytest.fixture
def tiny_checkpoint(tmp_path):
    path = tmp_path / "tiny.pt"
    save_tiny_checkpoint(path)
    return path


@pytest.fixture
def synthetic_pairs(tmp_path):
    path = tmp_path / "pairs.npz"
    save_pairs(path, make_pairs(sphere_shapes(3, 256), PairProtocol(points=256, keep=192), np.random.default_rng(0)))
    return path


def test_evaluate_writes_every_metric_to_json(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    out = tmp_path / "metrics.json"
    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(synthetic_pairs),
            "--json", str(out), "--batch-size", "2"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert set(metrics) == METRIC_KEYS
    assert metrics["n"] == 3
    assert all(np.isfinite(v) for v in metrics.values())
    assert 0.0 <= metrics["recall_r5_t005"] <= 1.0


def test_evaluate_writes_per_pair_poses_and_errors(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    out, per_pair = tmp_path / "metrics.json", tmp_path / "pairs_out.npz"
    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(synthetic_pairs), "--json", str(out),
            "--per-pair", str(per_pair), "--batch-size", "2"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    rows = np.load(per_pair)
    assert rows["rotation"].shape == (3, 3, 3) and rows["translation"].shape == (3, 3)
    gt = np.load(synthetic_pairs)
    expected = np.degrees(np.arccos(np.clip(
        (np.einsum("mij,mij->m", rows["rotation"], gt["rotation"]) - 1) / 2, -1, 1)))  # angle of R^T R_gt
    np.testing.assert_allclose(rows["rotation_error_deg"], expected, atol=1e-3)
    np.testing.assert_allclose(rows["translation_error"], np.linalg.norm(rows["translation"] - gt["translation"],
                                                                          axis=1), atol=1e-6)
    metrics = json.loads(out.read_text())  # the pooled figures are the same errors
    assert metrics["iso_r_median"] == pytest.approx(float(np.median(rows["rotation_error_deg"])), abs=1e-3)


def test_evaluate_reports_recall_by_label(tmp_path, tiny_checkpoint, synthetic_pairs) -> None:
    labelled = tmp_path / "labelled.npz"
    save_pairs(labelled, {**dict(np.load(synthetic_pairs)), "label": np.array([7, 3, 7])})
    out = tmp_path / "metrics.json"
    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--pairs", str(labelled), "--json", str(out),
            "--by-label", "--batch-size", "2"]
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


def test_evaluate_a_classical_baseline_on_the_same_pairs(tmp_path) -> None:
    pytest.importorskip("open3d", reason="the classical baselines need the bench extra (open3d-cpu)")
    shapes = np.random.default_rng(1).normal(size=(2, 2048, 3)) * [1.0, 0.6, 0.3]  # anisotropic blobs
    pairs_path, out = tmp_path / "pairs.npz", tmp_path / "fpfh.json"
    save_pairs(pairs_path, make_pairs(shapes.astype(np.float32), PairProtocol(points=2048, keep=1800),
                                      np.random.default_rng(2)))
    args = ["evaluate", "--baseline", "fpfh-ransac-icp", "--pairs", str(pairs_path), "--json", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert set(metrics) == METRIC_KEYS and metrics["n"] == 2 and metrics["ms_per_pair"] > 0
