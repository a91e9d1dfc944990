"""``python -m bench.queued_bodies``: peak server memory with every slot taken by a body of the largest size
(DEPLOYMENT's current figures), on a small server: its limits come from the ``MFGNET_*`` settings."""

from __future__ import annotations

import json

import pytest

from bench.queued_bodies import main, padded_body
from model.data import data_dir
from service.manifest import bundled_models_dir

pytestmark = [
    pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model"),
    pytest.mark.skipif(not data_dir().is_dir(), reason="ModelNet40 absent (set MFGNET_DATA)"),
]


def test_padded_body_is_the_pair_and_spaces_to_the_size() -> None:
    body = padded_body(100, 1 << 16)
    assert len(body) == 1 << 16 and body.endswith(b" ")
    pair = json.loads(body)
    assert len(pair["source"]) == len(pair["target"]) == 100
    with pytest.raises(ValueError, match="above"):
        padded_body(5000, 1 << 16)


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_every_slot_answered_and_the_peak_reported(tmp_path, monkeypatch) -> None:
    for name, value in {"MFGNET_MODELS": "general", "MFGNET_MAX_QUEUE": "2", "MFGNET_MAX_POINTS": "2000",
                        "MFGNET_MAX_BODY_BYTES": str(1 << 20), "MFGNET_MAX_BUFFERED_BYTES": str(2 << 20)}.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "queued.json"
    main(["--json", str(out)])
    report = json.loads(out.read_text())
    assert report["requests"] == 4 and report["body_bytes"] == 1 << 20 and report["points"] == 2000
    assert report["this"]["statuses"] == {"200": 4}
    assert 50 < report["this"]["peak_after_warm_up_mib"] <= report["this"]["peak_mib"] < 1024


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
def test_beside_aligned_downloads_the_queue_is_filled_once_both_workers_run_them(tmp_path, monkeypatch) -> None:
    for name, value in {"MFGNET_MODELS": "general", "MFGNET_MAX_QUEUE": "2", "MFGNET_MAX_POINTS": "2000",
                        "MFGNET_MAX_FILE_POINTS": "20000", "MFGNET_MAX_BODY_BYTES": str(1 << 20),
                        "MFGNET_MAX_BUFFERED_BYTES": str(2 << 20)}.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "queued.json"
    main(["--beside-aligned", "laz", "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["beside_aligned"] == "laz" and report["requests"] == 2  # the queue: both workers move the files
    assert report["this"]["statuses"] == {"200": 2} and report["this"]["aligned_downloads"] == 2
