"""``python -m export.bench_load`` end to end: two real servers taking turns, every row of the report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from export.bench_load import main
from service.manifest import bundled_models_dir

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


def test_two_servers_take_turns_and_answer_every_request(tmp_path) -> None:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(2, 300, 3)).astype(np.float32)
    pairs = tmp_path / "blobs.npz"
    np.savez(pairs, source=source, target=source + np.float32(0.05))
    out = tmp_path / "load.json"
    main(["--pairs", str(pairs), "--compare-root", str(ROOT), "--requests", "3", "--rounds", "2",
          "--concurrency", "1", "--concurrency", "2", "--threads", "1", "--json", str(out)])
    rows = json.loads(out.read_text())["rows"]
    order = [(row["round"], row["concurrency"], row["server"]) for row in rows]
    this, other = "(this checkout)", str(ROOT)
    assert order == [(0, 1, this), (0, 1, other), (0, 2, this), (0, 2, other),
                     (1, 1, other), (1, 1, this), (1, 2, other), (1, 2, this)]
    for row in rows:
        assert row["statuses"] == {"200": 3}  # JSON keys
        assert row["throughput_rps"] > 0 and 0 < row["p50_ms"] <= row["p95_ms"]
