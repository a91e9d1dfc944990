"""``mfgnet bench`` end to end on a tiny budget: every section of the report, and ``--compare``."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from model.data import data_dir
from service.cli import app
from service.manifest import bundled_models_dir

pytestmark = [
    pytest.mark.skipif(not (data_dir() / "modelnet40_test.npz").exists(),
                       reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)"),
    pytest.mark.skipif(not (bundled_models_dir() / "clean").is_dir(), reason="no bundled 'clean' model"),
]

TINY = ["--model", "clean", "--checkpoint", "clean", "--repeats", "2", "--http-requests", "0",
        "--accuracy-setting", "noise", "--accuracy-count", "2", "--no-classical"]


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_bench_reports_every_section_and_compares_with_a_baseline(tmp_path) -> None:
    out, baseline = tmp_path / "bench.json", tmp_path / "baseline.json"
    baseline.write_text(json.dumps({"pipeline_768": {"total": {"p50": 1000.0}}, "only_in_the_baseline": 1.0}))
    result = CliRunner().invoke(app, ["bench", *TINY, "--json", str(out), "--compare", str(baseline)])
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert report["pipeline_768"]["total"]["p50"] > 0
    for stage in ("preprocess", "encoder", "iterations", "svd", "postprocess"):
        assert report["pipeline_768"]["stages"][stage] > 0, stage  # median ms
    assert report["torch_eager_768"]["total"]["p50"] > 0 and report["speedup_vs_torch"] > 0
    assert set(report["iterations"]) == {str(n) for n in range(1, 7)}
    ablation = report["iteration_accuracy"]
    assert all(ablation[str(n)]["n"] == 2 and 0 <= ablation[str(n)]["recall_r5_t005"] <= 1 for n in range(1, 7))
    assert set(report["working_size"]) == {"512", "1024", "2048", "4096"}
    methods = report["accuracy"][0]["methods"]
    assert {"torch_eager", "onnx_pipeline", "onnx_pipeline_icp_plane", "onnx_auto_search_icp_plane"} <= set(methods)
    assert all(m["n"] == 2 and m["ms_per_pair"] > 0 for m in methods.values())

    # --compare: one line per figure in both reports, the baseline's value, this run's and the change
    p50 = report["pipeline_768"]["total"]["p50"]
    change = f"{100 * (p50 / 1000.0 - 1):+.1f}%"
    assert f"{'pipeline_768.total.p50':45s} {1000.0:10.3f} -> {p50:10.3f} ({change})" in result.output
    assert "only_in_the_baseline" not in result.output
