"""`python -m bench.http_latency`: in process beside HTTP, each size, each server, with where and from what."""

from __future__ import annotations

import json

import pytest
from provenance_check import assert_made_by_this_checkout

from bench.http_latency import main


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
