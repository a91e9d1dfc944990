"""bench.failures: each wrong result of the defaults classed by a run started at the true pose."""

from __future__ import annotations

import json

import pytest
from provenance_check import assert_made_by_this_checkout

from bench.failures import CLASSES, failure_class, main
from bench.real_scans import data_dir, thresholds
from service.registrar import default_threads

LOW_OVERLAP = "3dlo_kitchen_34_21"  # 11-14% overlap: neither the service nor FPFH + RANSAC + ICP registers it
DENSE = "dragon_24_0"  # registered as scanned and turned
needs_data = pytest.mark.skipif(not all((data_dir() / f"{p}.npz").exists() for p in (LOW_OVERLAP, DENSE)),
                                reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")


def test_the_classes_follow_the_run_from_the_truth() -> None:
    assert failure_class(truth_right=False, truth_ratio=0.9, wrong_ratio=0.1) == "truth leaves"
    assert failure_class(truth_right=True, truth_ratio=0.40, wrong_ratio=0.45) == "fits worse"
    assert failure_class(truth_right=True, truth_ratio=0.45, wrong_ratio=0.45) == "fits worse"  # a tie: no fit wins
    assert failure_class(truth_right=True, truth_ratio=0.51, wrong_ratio=0.44) == "not reached"


@needs_data
def test_only_wrong_results_are_examined_and_each_gets_its_class(tmp_path) -> None:
    out = tmp_path / "failures.json"
    report = main(["--pairs", LOW_OVERLAP, DENSE, "--seeds", "0", "--turns", "1", "--json", str(out)])
    assert report["cases"] == 4
    failed = {row["case"] for row in report["rows"]}
    assert f"{LOW_OVERLAP}/scanned/x1" in failed
    assert not any(case.startswith(DENSE) for case in failed)  # right results are not examined
    assert report["failures"] == len(report["rows"]) == sum(report["classes"].values())
    for row in report["rows"]:
        max_deg, max_error = thresholds(row["sensor"])
        assert not (row["rotation_error_deg"] < max_deg and row["translation_error"] < max_error)
        truth = row["from_truth"]
        stayed = truth["rotation_error_deg"] < max_deg and truth["translation_error"] < max_error
        assert row["class"] == failure_class(stayed, truth["inlier_ratio"], row["inlier_ratio"])
        assert row["class"] in CLASSES
    written = json.loads(out.read_text())
    assert written["classes"] == report["classes"]
    assert written["seeds"] == [0] and written["turns"] == 1 and written["scales"] == [1.0]  # how to rerun it
    assert_made_by_this_checkout(written["provenance"]) and "degrees" in written["units"]
    assert written["machine"]["threads"] == default_threads() and written["machine"]["cpus"] > 0
