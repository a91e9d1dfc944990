"""``python -m bench.settings``: each setting's options reach ``register`` and its figures are its own."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout
from shapes import ellipsoid_surface

from bench.real_scans import data_dir
from bench.settings import main, parse_setting
from model.data import PairProtocol, make_pairs, save_pairs
from service.manifest import bundled_models_dir

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "general").is_dir(), reason="no bundled 'general' model")


def test_every_setting_gets_its_own_row_with_accuracy_time_and_stages(tmp_path) -> None:
    rng = np.random.default_rng(0)
    shapes = ellipsoid_surface(rng, (2, 1024))
    save_pairs(tmp_path / "p.npz", make_pairs(shapes.astype(np.float32), PairProtocol(), rng))
    out = tmp_path / "settings.json"
    main(["--pairs", str(tmp_path / "p.npz"), "--setting", "{}", "--setting",
          '{"keypoints": 16, "iterations": 1, "refine": "none"}', "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["n"] == 2 and [row["options"] for row in report["settings"]] == [
        {"refine": "icp-plane"}, {"refine": "none", "keypoints": 16, "iterations": 1}]
    default, cheap = report["settings"]
    assert "refine" in default["stage_ms_median"] and "refine" not in cheap["stage_ms_median"]  # options applied
    for row in report["settings"]:
        assert 0 <= row["recall_r1_t001"] <= row["recall_r5_t005"] <= 1
        assert row["ms_per_pair_median"] >= row["stage_ms_median"]["encoder"] > 0


def test_a_setting_must_be_a_json_object() -> None:
    assert parse_setting('{"keypoints": 64}') == {"keypoints": 64}
    for bad in ("[1]", "keypoints=64", "64"):
        with pytest.raises(argparse.ArgumentTypeError, match="JSON object"):
            parse_setting(bad)


needs_scans = pytest.mark.skipif(not any(data_dir().glob("*.npz")),
                                 reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")


@needs_scans
def test_scans_registers_the_real_cases_with_each_setting_and_counts_successes(tmp_path) -> None:
    out = tmp_path / "scans.json"
    main(["--scans", str(data_dir()), "--count", "2", "--setting", '{"refine": "none", "rotation_search": false}',
          "--setting", '{"refine": "none", "rotation_search": true}', "--json", str(out)])
    report = json.loads(out.read_text())
    assert report["n"] == 2 and report["turns"] == 1 and report["scales"] == [1.0]  # how to rerun it
    first = report["cases"][0].split("/")[0]  # the set's first pair, as scanned and turned once
    assert report["cases"] == [f"{first}/scanned", f"{first}/turned"]
    plain, searched = report["settings"]
    assert "search" not in plain["stage_ms_median"] and "search" in searched["stage_ms_median"]  # options applied
    for row in report["settings"]:
        assert 0 <= row["successes"] <= 2 and row["ms_per_pair_median"] >= row["stage_ms_median"]["encoder"] > 0
        assert list(row["ms_per_pair_median_by_sensor"]) and all(
            ms > 0 for ms in row["ms_per_pair_median_by_sensor"].values())
    assert_made_by_this_checkout(report["provenance"])


def test_scans_and_pairs_are_one_or_the_other(tmp_path, capsys) -> None:
    for argv in (["--setting", "{}"], ["--pairs", str(tmp_path / "p.npz"), "--scans", "--setting", "{}"]):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["--scans", str(tmp_path), "--setting", "{}"])  # no *.npz pairs there
    assert exit_info.value.code == 2 and "no real-scan set" in capsys.readouterr().err
