"""``python -m bench.scan_reliability``: ``reliable`` on simulated range scans at any orientation (row H)."""

from __future__ import annotations

import json

import pytest
from pair_checks import needs_dense
from provenance_check import assert_made_by_this_checkout

from bench.report_io import reliable_totals as totals
from bench.scan_reliability import from_truth, kind, main, report
from service.registrar import default_threads


def row(success: bool, reliable: bool, degrees: float = 1.0, translation: float = 0.01, label: int = 0) -> dict:
    return {"seed": 5, "pair": 0, "label": label, "rotation_error_deg": degrees, "translation_error": translation,
            "success": success, "reliable": reliable}


def test_totals_count_precision_over_the_given_and_coverage_over_the_successes():
    rows = [row(True, True), row(True, True), row(True, False), row(False, True, 179.0), row(False, False, 90.0)]
    assert totals(rows) == {"cases": 5, "successes": 3, "reliable_given": 3, "reliable_wrong": 1,
                            "precision": pytest.approx(2 / 3, abs=1e-4), "coverage": pytest.approx(2 / 3, abs=1e-4)}
    assert totals([row(False, False)])["precision"] is None and totals([row(False, False)])["coverage"] is None


@pytest.mark.parametrize(("degrees", "translation", "expected"),
                         [(179.5, 0.1, "half turn"), (90.0, 0.02, "turned"), (5.0, 0.01, "turned"),
                          (0.3, 0.08, "slid")])
def test_a_wrong_result_is_named_by_how_it_is_wrong(degrees, translation, expected):
    assert kind(row(False, True, degrees, translation)) == expected


def test_the_report_lists_only_wrong_reliable_results_and_splits_by_class():
    rows = [row(True, True, label=0), row(False, True, 179.0, label=1), row(False, False, 179.0, label=1)]
    out = report(rows, ["airplane", "bathtub"])
    assert [(w["class"], w["kind"]) for w in out["reliable_wrong"]] == [("bathtub", "half turn")]
    assert out["by_class"]["airplane"]["reliable_wrong"] == 0 and out["by_class"]["bathtub"]["reliable_wrong"] == 1


@needs_dense
def test_the_benchmark_registers_seeded_scans_through_the_runtime(tmp_path):
    out = main(["--seeds", "5", "--count", "4", "--json", str(tmp_path / "r.json")])
    written = json.loads((tmp_path / "r.json").read_text())
    assert written["totals"] == out["totals"] and written["totals"]["cases"] == 4
    rows = written["rows"]
    assert len(rows) == 4 and all(r["seed"] == 5 for r in rows)
    assert all(r["success"] == (r["rotation_error_deg"] < 5 and r["translation_error"] < 0.05) for r in rows)
    assert sum(f["cases"] for f in written["by_class"].values()) == 4
    assert out["totals"]["successes"] >= 2  # the defaults register most of these at any orientation
    assert written["seeds"] == [5] and written["count"] == 4 and "degrees" in written["units"]
    assert_made_by_this_checkout(written["provenance"])
    assert written["machine"]["threads"] == default_threads() and written["machine"]["cpus"] > 0


def test_the_report_counts_wrong_reliable_results_by_failure_class():
    rows = [{**row(False, True, 179.0), "failure": "fits worse"}, {**row(False, True, 90.0), "failure": "not reached"},
            {**row(False, True, 179.0), "failure": "fits worse"}, row(True, True)]
    assert report(rows, None)["reliable_wrong_by_failure"] == {"truth leaves": 0, "fits worse": 2, "not reached": 1}


@needs_dense
def test_a_wrong_result_is_classed_by_a_registration_from_its_true_pose():
    from model.data import make_test_pairs, protocol_for
    from service.manifest import model_folder
    from service.registrar import Registrar

    pairs = make_test_pairs("scans", count=1, seed=5, protocol=protocol_for("scans", max_angle=180))
    registrar = Registrar(model_folder("general"))
    # a made-up wrong result that fitted perfectly: the truth, staying right, fits no better
    worse = from_truth(registrar, pairs, {**row(False, True, 179.0), "inlier_ratio": 1.0})
    # ... and one that fitted nothing: the truth fits better, so no candidate reached it
    unreached = from_truth(registrar, pairs, {**row(False, True, 179.0), "inlier_ratio": 0.0})
    assert worse["failure"] == "fits worse" and unreached["failure"] == "not reached"
    assert worse["from_truth"] == unreached["from_truth"]
    assert worse["from_truth"]["rotation_error_deg"] < 5 and 0 < worse["from_truth"]["inlier_ratio"] <= 1
