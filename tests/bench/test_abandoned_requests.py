"""``python -m bench.abandoned_requests``: default requests among abandoned searches, against a real server."""

from __future__ import annotations

import json

import pytest

from bench.abandoned_requests import main
from model.data import data_dir
from service.manifest import bundled_models_dir

pytestmark = [
    pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model"),
    pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)"),
    pytest.mark.serial,  # deadlines and client timeouts: timing-sensitive, run alone
    pytest.mark.slow,  # the benchmark's whole run, on demand (make test-all; decisions/0098); test_reliability_faults
    # checks in CI that a client that goes away frees its worker
]


def test_abandoned_searches_leave_the_server_free(tmp_path) -> None:
    out = tmp_path / "abandoned.json"
    main(["--requests", "10", "--clients", "4", "--json", str(out)])
    (server,) = json.loads(out.read_text())["servers"]
    kinds = {key.split()[0] for key in server["statuses"]}
    assert kinds <= {"default", "impatient", "heavy"} and sum(server["statuses"].values()) == 10
    assert not any(key.startswith("heavy 200") for key in server["statuses"])  # tens of seconds: past the deadline
    assert server["default_answers_have_the_servers_pose"]
    assert server["slots_taken_2s_after"] == 0 and server["a_default_request_after"] == 200
