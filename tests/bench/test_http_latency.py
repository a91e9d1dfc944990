"""`python -m bench.http_latency`: in process beside HTTP, each size, each server, with where and from what."""

from __future__ import annotations

import json

import pytest
from provenance_check import assert_made_by_this_checkout

from bench.http_latency import main
from model.data import data_dir
from service.manifest import bundled_models_dir

pytestmark = [
    pytest.mark.skipif(not (data_dir() / "modelnet40_test.npz").exists(),
                       reason=f"ModelNet40 not found at {data_dir()} (set $MFGNET_DATA)"),
    pytest.mark.skipif(not (bundled_models_dir() / "clean").is_dir(), reason="no bundled 'clean' model"),
]


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_the_report_times_every_size_and_says_where_and_from_what(tmp_path) -> None:
    out = tmp_path / "overhead.json"
    main(["--requests", "2", "--big-requests", "1", "--threads", "1", "--json", str(out)])
    report = json.loads(out.read_text())
    (server,) = report["servers"]
    assert server["server_root"] == "(this checkout)" and report["in_process_768_p50_ms"] > 0
    for size in ("768", "20000", "100000"):
        for kind in ("json", "bytes"):
            assert server[f"http_{size}_{kind}_p50_ms"] > 0, (size, kind)
    assert server["rss_mb_peak"] >= server["rss_mb_after_start"] > 0
    assert report["machine"]["threads"] == 1 and report["machine"]["cpus"] > 0
    assert_made_by_this_checkout(report["provenance"], "clean")  # the model every server gets
