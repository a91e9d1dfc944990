"""``python -m bench.load`` end to end: two real servers taking turns, every row of the report."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout

from bench.load import main, parse_setting
from service.manifest import bundled_models_dir

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_two_servers_take_turns_and_answer_every_request(tmp_path) -> None:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(2, 300, 3)).astype(np.float32)
    pairs = tmp_path / "blobs.npz"
    np.savez(pairs, source=source, target=source + np.float32(0.05))
    out = tmp_path / "load.json"
    main(["--pairs", str(pairs), "--compare-root", str(ROOT), "--requests", "3", "--rounds", "2",
          "--concurrency", "1", "--concurrency", "2", "--settings", "1x1", "--json", str(out)])
    written = json.loads(out.read_text())
    rows = written["rows"]
    order = [(row["round"], row["concurrency"], row["server"]) for row in rows]
    this, other = "(this checkout), 1x1", f"{ROOT}, 1x1"
    assert order == [(0, 1, this), (0, 1, other), (0, 2, this), (0, 2, other),
                     (1, 1, other), (1, 1, this), (1, 2, other), (1, 2, this)]
    for row in rows:
        assert row["statuses"] == {"200": 3}  # JSON keys
        assert row["throughput_rps"] > 0 and 0 < row["p50_ms"] <= row["p95_ms"]
    assert written["machine"]["threads"] == 1 and written["machine"]["cpus"] > 0  # --settings 1x1
    assert_made_by_this_checkout(written["provenance"])  # the default request's model


def test_settings_name_threads_and_concurrency() -> None:
    assert parse_setting("2x4") == (2, 4) and parse_setting("1X2") == (1, 2)
    for bad in ("2", "ax2", "0x2", "2x2x2"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"THREADSxCONCURRENCY|>= 1"):
            parse_setting(bad)
