"""The altered real pairs: each alteration does what it says, keeps the pair's frames, and is seeded."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout

from bench.altered_scans import ALTERATIONS, CROP_KEEP, altered, cases, main
from bench.real_scans import data_dir, fpfh_threads
from service.registrar import default_threads

PAIR = "dragon_48_24"


def _cloud(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, 3)).astype(np.float32)


def test_each_alteration_does_what_it_says():
    source, target = _cloud(10_000, 0), _cloud(8000, 1)
    rng = np.random.default_rng(2)
    sparse_s, sparse_t = altered("sparse10", source, target, rng)
    assert 800 < len(sparse_s) < 1200 and 600 < len(sparse_t) < 1000 and np.isin(sparse_s, source).all()
    noisy_s, noisy_t = altered("noise", source, target, rng)
    assert noisy_s.shape == source.shape and noisy_t.shape == target.shape
    assert 0 < np.abs(noisy_s - source).mean() < 0.1
    cropped, same = altered("crop", source, target, rng)
    assert abs(len(cropped) - CROP_KEEP * len(source)) <= 1 and same is target
    whole, cut = altered("croptarget", source, target, rng)
    assert abs(len(cut) - CROP_KEEP * len(target)) <= 1 and whole is source and np.isin(cut, target).all()
    sparse_source, whole = altered("source10", source, target, rng)
    assert 800 < len(sparse_source) < 1200 and np.isin(sparse_source, source).all() and whole is target
    more_s, more_t = altered("scattered", source, target, rng, scattered=0.2)
    assert len(more_s) == 12_000 and np.array_equal(more_s[:10_000], source) and len(more_t) == 9600
    assert (more_s.min(axis=0) >= source.min(axis=0)).all() and (more_s.max(axis=0) <= source.max(axis=0)).all()
    with pytest.raises(ValueError, match="unknown alteration"):
        altered("blur", source, target, rng)


@pytest.mark.skipif(not (data_dir() / f"{PAIR}.npz").exists(),
                    reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")
@pytest.mark.parametrize("kind", ALTERATIONS)
def test_the_cases_are_seeded_and_the_turned_one_keeps_the_truth(kind: str):
    first, again = list(cases(data_dir(), kind, names=[PAIR])), list(cases(data_dir(), kind, names=[PAIR]))
    assert [c[0] for c in first] == [f"{kind}/{PAIR}/scanned", f"{kind}/{PAIR}/turned"]
    for one, two in zip(first, again, strict=True):
        assert all(np.array_equal(a, b) for a, b in zip(one[2:5], two[2:5], strict=True))
    (_, _, src, _, truth, _), (_, _, src_t, _, truth_t, _) = first
    moved = [c.astype(np.float64) @ T[:3, :3].T + T[:3, 3] for c, T in ((src, truth), (src_t, truth_t))]
    assert np.abs(moved[0] - moved[1]).max() < 1e-5  # both land on the same points of the target's frame


@pytest.mark.skipif(not (data_dir() / f"{PAIR}.npz").exists(),
                    reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)")
def test_the_run_registers_each_case_with_both_methods_and_totals_them(tmp_path):
    pytest.importorskip("open3d", reason="FPFH + RANSAC + ICP needs the bench extra")
    out = tmp_path / "altered.json"
    report = main(["--alterations", "sparse10", "--pairs", PAIR, "--json", str(out)])
    rows, figures = report["rows"], report["totals"]["sparse10"]
    assert [r["variant"] for r in rows] == [f"sparse10/{PAIR}/scanned", f"sparse10/{PAIR}/turned"]
    assert figures["cases"] == 2 and figures["service_successes"] == sum(r["service_success"] for r in rows)
    assert figures["fpfh_successes"] == sum(r["fpfh_success"] for r in rows)
    assert figures["reliable_wrong"] == sum(r["reliable"] and not r["service_success"] for r in rows)
    assert all(r["service_seconds"] > 0 and r["fpfh_seconds"] > 0 for r in rows)
    written = json.loads(out.read_text())
    assert written["totals"]["sparse10"] == figures
    assert (written["machine"]["cpus"], written["machine"]["threads"]) == (os.cpu_count(), default_threads())
    assert written["machine"]["fpfh_threads"] == fpfh_threads()  # FPFH + RANSAC + ICP's, beside the service's
    assert_made_by_this_checkout(written["provenance"])  # bench.variant_runs' report, as lidar_variants writes it



def test_a_pair_files_own_thresholds_come_with_its_altered_cases(tmp_path):
    """They were dropped: a `lidar` pair in millimetres was judged by the metre thresholds, and a sensor of no class
    ended the run in a traceback (`bench.variant_runs.registered` takes a case's own thresholds first)."""
    cloud = _cloud(400, 3)
    np.savez(tmp_path / "mine_1_0.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="lidar",
             rotation_threshold_deg=2.0, translation_threshold=0.005)
    yielded = list(cases(tmp_path, "sparse30"))
    assert [c[0] for c in yielded] == ["sparse30/mine_1_0/scanned", "sparse30/mine_1_0/turned"]
    assert [c[5] for c in yielded] == [(2.0, 0.005), (2.0, 0.005)]
