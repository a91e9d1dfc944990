"""``python -m bench.full_resolution``: time, server memory and upload parse of full-resolution clouds (REAL_SCANS'
and DEPLOYMENT's figures), run here on small clouds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.full_resolution import PARSE_FORMATS, full_resolution_pair, main, rotation_error_deg
from service.manifest import bundled_models_dir

needs_model = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


def test_the_pair_is_two_samples_of_one_surface_turned_by_the_rotation_it_returns() -> None:
    source, target, rotation = full_resolution_pair(0, 25.0, 5000)
    assert source.shape == target.shape == (5000, 3) and source.dtype == target.dtype == np.float32
    assert not np.allclose(source @ rotation.T, target - [0.2, -0.1, 0.05], atol=1e-3)  # independent samples
    centred = target - [0.2, -0.1, 0.05]
    assert np.allclose(np.sort(np.linalg.norm(centred, axis=1)), np.sort(np.linalg.norm(source, axis=1)), atol=0.05)
    assert rotation_error_deg(rotation, rotation) == pytest.approx(0.0, abs=1e-4)
    assert rotation_error_deg(np.eye(3), rotation) > 25.0


@pytest.mark.parametrize(("argv", "words"), [(["--points", "999"], "from 1000"), (["--points", "2000001"], "2000000"),
                                             (["--parts", "memory,speed"], "in_process, memory, parse"),
                                             (["--runs", "0"], "at least 1")])
def test_bad_arguments_are_usage_errors(capsys, argv, words) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2 and words in capsys.readouterr().err


@needs_model
def test_timing_and_parse_are_reported_from_real_registrations_and_uploads(tmp_path) -> None:
    out = tmp_path / "full_resolution.json"
    main(["--points", "20000", "--runs", "1", "--repeats", "1", "--parts", "in_process,parse", "--json", str(out)])
    report = json.loads(out.read_text())
    (timed,) = report["in_process"]
    assert len(timed["seconds"]) == 1 and timed["seconds"][0] > 0 and timed["rotation_error_deg"] < 1.0
    (parsed,) = report["parse_seconds"]
    assert set(parsed) == {*PARSE_FORMATS, "plyfile_ascii_in_process"} and min(parsed.values()) > 0
    assert report["upload_mib"]["ply-ascii"] > report["upload_mib"]["npy"] > 0 and "memory" not in report


@needs_model
@pytest.mark.slow  # a benchmark's whole run: two servers, one with every bundled model (make test-all; 0098)
def test_memory_is_the_peak_of_servers_that_registered_the_uploads(tmp_path) -> None:
    out = tmp_path / "full_resolution.json"
    main(["--points", "20000", "--runs", "1", "--parts", "memory", "--json", str(out)])
    (memory,) = json.loads(out.read_text())["memory"]
    assert 50 < memory["one_request_one_model_mib"] < memory["two_requests_manifest_mib"] < 2048
    assert len(memory["rotation_errors_deg"]) == 3 and max(memory["rotation_errors_deg"]) < 1.0
