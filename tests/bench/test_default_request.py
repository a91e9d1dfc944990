"""``python -m bench.default_request``: default requests to two real servers taking turns."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from provenance_check import assert_made_by_this_checkout

from bench.default_request import main
from model.data import data_dir
from service.manifest import bundled_models_dir

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [
    pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model"),
    pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)"),
]


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_both_servers_answer_every_default_request(tmp_path) -> None:
    out = tmp_path / "default_request.json"
    main(["--compare-root", str(ROOT), "--requests", "3", "--pairs", "2", "--json", str(out)])
    report = json.loads(out.read_text())
    assert [row["server_root"] for row in report["servers"]] == ["(this checkout)", str(ROOT)]
    for row in report["servers"]:
        assert 0 < row["p50_ms"] <= row["p95_ms"] and 0 <= row["searched"] <= 3
    assert report["p50_ratio_to_first_compared"] > 0
    assert_made_by_this_checkout(report["provenance"])
