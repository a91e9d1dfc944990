"""``python -m bench.refine_http`` end to end: a real server, both request kinds, the report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.refine_http import main
from service.manifest import bundled_models_dir

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "clean").is_dir(), reason="no bundled 'clean' model")


def test_reports_default_and_network_only_requests_of_every_file(tmp_path, capsys) -> None:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(2, 200, 3)).astype(np.float32)
    pairs = tmp_path / "blobs.npz"
    np.savez(pairs, source=source, target=source + np.float32(0.05))
    out = tmp_path / "report.json"
    main(["--pairs", str(pairs), "--model", "clean", "--count", "2", "--rounds", "1", "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["model"] == "clean" and json.loads(capsys.readouterr().out) == report
    kinds = report["results"]["blobs"]
    assert set(kinds) == {"default", "none"}
    for figures in kinds.values():
        assert figures["requests"] == 2
        assert 0 < figures["server_total_p50_ms"] < figures["http_p50_ms"] <= figures["http_p95_ms"]
