"""``python -m bench.server_memory``: a real server's memory through default requests (DEPLOYMENT's current figures)."""

from __future__ import annotations

import json

import pytest

from bench.server_memory import main
from model.data import data_dir
from service.manifest import bundled_models_dir

pytestmark = [
    pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model"),
    pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)"),
]


def test_one_model_server_reports_its_memory_at_each_phase(tmp_path) -> None:
    out = tmp_path / "server_memory.json"
    main(["--models", "general", "--small", "2", "--big-points", "5000", "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["models"] == ["general"] and report["small_requests"] == 2 and report["big_points"] == 5000
    rss = report["rss_mib"]
    assert 50 < rss["after_start"] < 1024  # a loaded model, not an empty interpreter nor a runaway
    assert max(rss["after_start"], rss["after_small"], rss["after_big"]) <= rss["peak"]


def test_aligned_downloads_report_each_server_peak(tmp_path) -> None:
    out = tmp_path / "aligned.json"
    options = ["--models", "general", "--aligned", "ply", "--aligned-pair", "laz", "--aligned-points", "3000"]
    main([*options, "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["points"] == 3000 and list(report["formats"]) == ["ply"] and report["pair"]["format"] == "laz"
    for run in (report["formats"]["ply"], report["pair"]):
        assert run["answer_mib"] > 0  # the moved file came back
        rss = run["rss_mib"]
        assert 50 < rss["after_start"] <= rss["peak"] and rss["after"] <= rss["peak"]
    pair = report["pair"]
    assert (pair["at_once"], pair["threads"], pair["max_concurrency"]) == (2, 1, 2)  # the manifest's settings
