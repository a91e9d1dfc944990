"""``mfgnet evaluate --model NAME`` evaluates a bundled ONNX model through the runtime pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapes import ellipsoid_surface
from typer.testing import CliRunner

from model.data import PairProtocol, make_pairs, save_pairs
from service.cli import app
from service.manifest import bundled_models_dir

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").exists(),
                                reason="bundled model 'clean' absent")


def test_evaluate_model_through_the_runtime_writes_the_metrics(tmp_path):
    rng = np.random.default_rng(0)
    shapes = ellipsoid_surface(rng, (3, 1024), bump=0.0)
    save_pairs(tmp_path / "p.npz", make_pairs(shapes.astype(np.float32), PairProtocol(), rng))
    out = tmp_path / "m.json"
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", "icp", "--pairs",
                                      str(tmp_path / "p.npz"), "--json", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert metrics["n"] == 3 and metrics["ms_per_pair"] > 0 and np.isfinite(metrics["mae_r"])


def test_evaluate_needs_exactly_one_of_checkpoint_or_model():
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--checkpoint", "clean"])
    assert result.exit_code != 0 and "exactly one" in result.output
