"""Load on the loopback with ``load_driver.py``: only 200s and the designed 503s, every 200 equal to the
sequential answer, 503s fast, and the server's memory flat. A short run in CI; a multi-minute run at
saturation with ``-m slow`` (figures in docs/RELIABILITY.md)."""

from __future__ import annotations

import asyncio
import json
import os

import pytest
from api_server import LIMITED, limited_server, start_subprocess_server
from load_driver import drive

pytestmark = pytest.mark.serial  # load at saturation: `make test` runs it alone, after the rest

CHEAP = {"iterations": 1, "keypoints": 16}


def check(report, rss_growth_mib: float) -> None:
    print(json.dumps(report.__dict__, indent=1))  # shown with -s, and on failure
    assert report.errors == 0, (report.statuses, report.transport_errors)
    assert set(report.statuses) <= {"200", "503"}, report.statuses
    assert report.statuses.get("200", 0) > 0
    assert report.mismatches == 0  # concurrent answers equal the sequential ones
    if report.latency_503_ms:
        assert report.latency_503_ms["p99"] < 1000, report.latency_503_ms  # refusals are quick
    before, after = report.rss_kib["before"], report.rss_kib["after"]
    assert (after - before) / 1024 < rss_growth_mib, report.rss_kib


def test_short_load_at_saturation_gives_only_200_and_503():
    """The limited server (one worker, no queue) under 4 closed-loop clients for 6 s."""
    server = limited_server()
    report = asyncio.run(drive(
        server.url, seconds=6, concurrency=4, max_requests=2_000, pid=server.extra["proc"].pid, points=300,
        options=CHEAP, headers={"Authorization": f"Bearer {LIMITED['api_key']}"},
    ))
    check(report, rss_growth_mib=48)
    assert report.statuses.get("503", 0) > 0  # saturated: the queue bound was hit


@pytest.mark.slow
def test_three_minutes_at_saturation():
    """Default options, 2 workers + 4 queued, 16 clients, 180 s (MFGNET_LOAD_SECONDS overrides)."""
    seconds = float(os.environ.get("MFGNET_LOAD_SECONDS", "180"))
    server = start_subprocess_server("load-slow", MFGNET_MAX_CONCURRENCY="2", MFGNET_MAX_QUEUE="4")
    try:
        report = asyncio.run(drive(server.url, seconds=seconds, concurrency=16, pid=server.extra["proc"].pid))
    finally:
        server.stop()
    # RSS rises once in the first seconds (ONNX Runtime arenas for concurrent runs), then must stay flat.
    check(report, rss_growth_mib=160)
    plateau = [kib for t, kib in report.rss_timeline_kib if t >= 20]
    assert (max(plateau) - plateau[0]) / 1024 < 16, report.rss_timeline_kib
    assert report.elapsed_s >= seconds
