"""Specification of what an operator reads: the access log lines and the ``/metrics`` series of the main real server
(``api_server.py``), as a log shipper and a Prometheus scrape see them."""

from __future__ import annotations

import random
import re
import string


def series(text: str) -> set[str]:
    return {line.rsplit(" ", 1)[0] for line in text.splitlines() if line and not line.startswith("#")}


def test_a_thousand_unknown_paths_add_no_series(client):
    rng = random.Random(0)
    for method in ("GET", "POST", "PUT", "DELETE"):  # each method's <unmatched> 404 series exists first
        client.request(method, "/warm-up")
    client.get("/metrics")  # and the scrape's own
    before = series(client.get("/metrics").text)
    for i in range(1000):
        path = "/" + "".join(rng.choices(string.ascii_letters + string.digits, k=12)) + f"/{i}?token=secret{i}"
        assert client.request(rng.choice(["GET", "POST", "PUT", "DELETE"]), path).status_code == 404
    text = client.get("/metrics").text
    assert series(text) == before
    assert "secret" not in text


def test_metrics_export_no_created_series(client):
    """prometheus_client's ``_created`` gauges doubled the counters' series and were in no table."""
    text = client.get("/metrics").text
    assert not re.search(r"^mfgnet_\w+_created", text, flags=re.MULTILINE)
