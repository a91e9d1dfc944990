"""``mfgnet evaluate --model NAME`` evaluates a bundled ONNX model through the runtime pipeline."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout
from shapes import ellipsoid_surface
from typer.testing import CliRunner

from model.data import PairProtocol, make_pairs, save_pairs
from service.cli import app
from service.manifest import bundled_models_dir
from service.registrar import default_threads

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").exists(),
                                reason="bundled model 'clean' absent")


@pytest.mark.parametrize("refine", ["icp", "icp-plane"])
def test_evaluate_model_through_the_runtime_writes_the_metrics(tmp_path, refine):
    rng = np.random.default_rng(0)
    shapes = ellipsoid_surface(rng, (3, 1024), bump=0.0)
    save_pairs(tmp_path / "p.npz", make_pairs(shapes.astype(np.float32), PairProtocol(), rng))
    out = tmp_path / "m.json"
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", refine, "--pairs",
                                      str(tmp_path / "p.npz"), "--json", str(out)])
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert metrics["n"] == 3 and metrics["ms_per_pair"] > 0 and np.isfinite(metrics["mae_r"])
    manifest = json.loads((bundled_models_dir() / "clean" / "manifest.json").read_text())
    evaluated = metrics["evaluated"]  # what was measured: the model, the checkpoint it came from, the options
    assert (evaluated["model"], evaluated["model_version"]) == ("clean", manifest["version"])
    assert evaluated["checkpoint_sha256"] == manifest["source_checkpoint_sha256"]
    assert (evaluated["refine"], evaluated["rotation_search"]) == (refine, False)
    assert evaluated["iterations"] == manifest["config"]["iterations"]
    assert (evaluated["machine"]["cpus"], evaluated["machine"]["threads"]) == (os.cpu_count(), default_threads())
    assert_made_by_this_checkout(evaluated["provenance"], "clean")


def spy_on_register(monkeypatch, option: str) -> list:
    """The values of ``option`` that ``Registrar.register`` receives (warm-up calls, which pass none, skipped)."""
    import service.registrar

    seen = []
    real = service.registrar.Registrar.register

    def spy(self, *args, **kwargs):
        if "refine" in kwargs:  # not the warm-up call
            seen.append(kwargs[option])
        return real(self, *args, **kwargs)

    monkeypatch.setattr(service.registrar.Registrar, "register", spy)
    return seen


def two_pairs_file(tmp_path, seed: int):
    """Two seeded ellipsoid pairs written as a pairs file."""
    rng = np.random.default_rng(seed)
    shapes = ellipsoid_surface(rng, (2, 1024))
    save_pairs(tmp_path / "p.npz", make_pairs(shapes.astype(np.float32), PairProtocol(), rng))
    return tmp_path / "p.npz"


def test_evaluate_passes_icp_plane_to_the_runtime(tmp_path, monkeypatch):
    seen = spy_on_register(monkeypatch, "refine")
    two_pairs_file(tmp_path, 1)
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", "icp-plane", "--iterations", "1",
                                      "--pairs", str(tmp_path / "p.npz")])
    assert result.exit_code == 0, result.output
    assert seen == ["icp-plane", "icp-plane"]


def test_evaluate_rejects_an_unknown_refine_mode(tmp_path):
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", "plane", "--pairs",
                                      str(tmp_path / "missing.npz")])
    assert result.exit_code != 0 and "icp-plane" in result.output


def test_evaluate_needs_exactly_one_of_checkpoint_or_model():
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--checkpoint", "clean"])
    assert result.exit_code != 0 and "exactly one" in result.output


def test_evaluate_rotation_search_mode_auto_reports_the_share_of_pairs_searched(tmp_path, monkeypatch):
    seen = spy_on_register(monkeypatch, "rotation_search")
    two_pairs_file(tmp_path, 2)
    out = tmp_path / "m.json"
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", "icp", "--rotation-search-mode",
                                      "auto", "--pairs", str(tmp_path / "p.npz"), "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert seen == ["auto", "auto"]
    metrics = json.loads(out.read_text())
    assert metrics["rotation_search_share"] in (0.0, 0.5, 1.0)
    assert metrics["reliable_share"] in (0.0, 0.5, 1.0)  # each result's quality.reliable, counted
    assert metrics["reliable_wrong_share"] <= metrics["reliable_share"]
    assert metrics["reliable_wrong_share"] + metrics["unreliable_right_share"] <= 1.0


def test_evaluate_rejects_contradicting_rotation_search_options(tmp_path):
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--rotation-search", "--rotation-search-mode",
                                      "off", "--pairs", str(tmp_path / "missing.npz")])
    assert result.exit_code == 2 and "contradicts" in result.output


def test_evaluate_model_per_pair_has_each_results_reliable_flag_and_stability(tmp_path):
    pairs = two_pairs_file(tmp_path, 3)
    out, per_pair = tmp_path / "m.json", tmp_path / "rows.npz"
    result = CliRunner().invoke(app, ["evaluate", "--model", "clean", "--refine", "icp-plane", "--pairs", str(pairs),
                                      "--json", str(out), "--per-pair", str(per_pair)])
    assert result.exit_code == 0, result.output
    rows, metrics = np.load(per_pair), json.loads(out.read_text())
    assert rows["reliable"].dtype == bool and rows["reliable"].shape == (2,)
    assert rows["reliable"].mean() == pytest.approx(metrics["reliable_share"])  # the flags the metrics counted
    assert rows["stability"].shape == (2,) and np.all(np.isfinite(rows["stability"]) & (rows["stability"] >= 0))
    right = (rows["rotation_error_deg"] < 5.0) & (rows["translation_error"] < 0.05)
    misled = metrics["warnings_by_outcome"]  # per outcome: how many carried each set of warning kinds
    assert sum(misled["right_unreliable"].values()) == np.sum(right & ~rows["reliable"])
    assert sum(misled["wrong_reliable"].values()) == np.sum(~right & rows["reliable"])
