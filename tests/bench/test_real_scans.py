"""bench.real_scans: the service half through a real server on one real pair; Open3D's half where installed."""

import os
from pathlib import Path

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout
from scipy.spatial.transform import Rotation

from bench import real_scans

DATA = real_scans.data_dir()
PAIR = "dragon_24_0"  # a small range-image pair that the service registers as scanned
needs_data = pytest.mark.skipif(not (DATA / f"{PAIR}.npz").exists(),
                                reason=f"real-scan set absent ({DATA}; set MFGNET_REAL_DATA)")


def test_turned_ground_truth_maps_the_turned_source_onto_the_target():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(50, 3)).astype(np.float32)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1.0, 2.0, 3.0]
    target = source @ truth[:3, :3].T + truth[:3, 3]
    moved, moved_truth = real_scans.turned(source, truth, Rotation.random(random_state=1).as_matrix())
    assert np.abs(moved - source).max() > 0.1
    np.testing.assert_allclose(moved @ moved_truth[:3, :3].T + moved_truth[:3, 3], target, atol=1e-5)


def test_more_turns_add_variants_and_keep_the_first_turn(tmp_path):
    rng = np.random.default_rng(2)
    for name in ("a", "b"):
        cloud = rng.normal(size=(40, 3)).astype(np.float32)
        np.savez(tmp_path / f"{name}.npz", source=cloud, target=cloud + 1.0, transform=np.eye(4),
                 sensor="cyberware-range")
    one = real_scans.load_cases(tmp_path, seed=3, scales=(1.0,))
    three = real_scans.load_cases(tmp_path, seed=3, scales=(1.0,), turns=3)
    assert [c.variant for c in one] == ["scanned", "turned"] * 2
    assert [(c.name, c.variant) for c in three] == [(n, v) for n in "ab" for v in ("scanned", "turned", "turned-2",
                                                                                  "turned-3")]
    first = {c.name: c.source for c in one if c.variant == "turned"}
    for case in three:
        if case.variant == "turned":
            np.testing.assert_array_equal(case.source, first[case.name])  # the same as with one turn
    b = [c.source for c in three if c.name == "b"]
    assert all(np.abs(b[i] - b[j]).max() > 0.1 for i in range(4) for j in range(i))  # four different poses


def test_cases_moved_away_are_judged_in_their_own_frames():
    rng = np.random.default_rng(4)
    source = rng.normal(size=(30, 3)).astype(np.float32)
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = Rotation.from_euler("zx", [40, -10], degrees=True).as_matrix(), [0.5, 0.0, 0.2]
    case = real_scans.Case("p", "cyberware-range", "scanned", 1.0, source, source @ truth[:3, :3].T + truth[:3, 3],
                           truth)
    offset = np.array([1000.0, -2000.0, 500.0])
    far = real_scans.moved_away([case], offset)[0]
    assert far.source.dtype == np.float32 and np.abs(far.source - source - offset).max() < 1e-3  # float32 rounding
    R, t = truth[:3, :3], truth[:3, 3] + offset - truth[:3, :3] @ offset  # the true pose between the moved clouds
    np.testing.assert_allclose(far.source @ R.T + t, far.target, atol=2e-3)
    # a pose a degree off about the moved source's centroid: a few mm at the data, 40 m at the far origin
    D = Rotation.from_euler("z", 1, degrees=True).as_matrix()
    centre = far.source.mean(axis=0, dtype=np.float64) @ R.T + t
    R1, t1 = D @ R, D @ (t - centre) + centre
    judged = real_scans.judged(far, R1, t1)
    assert judged["rotation_error_deg"] == pytest.approx(1.0, abs=1e-6) and judged["translation_error"] < 0.1
    assert real_scans.pose_errors(R1, t1, np.r_[np.c_[R, t], [[0, 0, 0, 1]]])[1] > 10  # as judged at the offset
    assert real_scans.judged(far, R, t)["success"] and not real_scans.judged(case, R, t)["success"]


def test_thresholds_scale_with_the_unit():
    assert real_scans.thresholds("cyberware-range", 1000.0) == (5.0, 10.0)
    assert real_scans.thresholds("kinect-fused-2.5cm") == (15.0, 0.3)
    assert real_scans.thresholds("xtion-fused-2.5cm", 1000.0) == (15.0, 300.0)
    assert real_scans.thresholds("lidar") == (5.0, 2.0)


def test_a_sensor_of_no_class_is_refused_before_any_registration(tmp_path, capsys):
    """A set whose sensors the data README gives no thresholds for is not judged by the indoor ones silently."""
    with pytest.raises(ValueError, match="'velodyne-hdl64' is of no class"):
        real_scans.thresholds("velodyne-hdl64")
    cloud = np.random.default_rng(0).normal(size=(40, 3)).astype(np.float32)
    np.savez(tmp_path / "frames.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="velodyne-hdl64")
    with pytest.raises(SystemExit):
        real_scans.main([str(tmp_path), "--no-fpfh", "--url", "http://127.0.0.1:9"])  # nothing listens there
    assert "sensor 'velodyne-hdl64' is of no class with success thresholds" in capsys.readouterr().err


def test_pose_errors():
    truth = np.eye(4)
    R = Rotation.from_euler("x", 10, degrees=True).as_matrix()
    r_err, t_err = real_scans.pose_errors(R, np.array([0.0, 3.0, 4.0]), truth)
    assert r_err == pytest.approx(10.0) and t_err == pytest.approx(5.0)


def test_precision_is_compared_on_the_cases_both_methods_register():
    cloud = np.zeros((3, 3), np.float32)
    sensors = ["cyberware-range", "cyberware-range", "kinect-fused-2.5cm", "cyberware-range"]
    cases = [real_scans.Case(f"p{i}", s, "scanned", 1.0, cloud, cloud, np.eye(4)) for i, s in enumerate(sensors)]

    def row(degrees: float, error: float, success: bool = True) -> dict:
        return {"rotation_error_deg": degrees, "translation_error": error, "success": success}

    service = [row(0.2, 0.001), row(0.4, 0.003), row(2.0, 0.15), row(0.1, 0.0001)]
    fpfh = [row(0.6, 0.002), row(0.8, 0.004), row(4.0, 0.03), row(170.0, 1.0, success=False)]
    entry = real_scans.precision_where_both_right(cases, service, fpfh)  # the last case: FPFH missed it
    assert entry == {"both_right": 3, "service_median_rotation_error_deg": 0.4, "service_median_translation_share": 0.3,
                     "fpfh_median_rotation_error_deg": 0.8, "fpfh_median_translation_share": 0.2}


@needs_data
def test_service_half_registers_a_real_pair_over_http(tmp_path):
    out = tmp_path / "real.json"
    report = real_scans.main([str(DATA), "--pairs", PAIR, "--no-fpfh", "--scales", "1", "1000",
                              "--json", str(out)])
    assert out.exists()
    rows = report["pairs"]
    assert [(r["variant"], r["scale"]) for r in rows] == [("scanned", 1.0), ("turned", 1.0),
                                                          ("scanned", 1000.0), ("turned", 1000.0)]
    scanned = rows[0]["service"]
    assert scanned["status"] == 200 and scanned["success"] and scanned["rotation_error_deg"] < 5
    assert "fpfh_threads" not in report["machine"]  # FPFH + RANSAC + ICP did not run
    for scale in ("x1", "x1000"):
        assert report["totals"][scale]["cases"] == 2 and report["totals"][scale]["service_seconds"] > 0
        stages = report["totals"][scale]["stage_seconds"]  # the server's own time, summed per stage
        assert {"preprocess", "encoder", "refine", "postprocess", "total"} <= set(stages)
        assert 0 < stages["preprocess"] < stages["total"] <= report["totals"][scale]["service_seconds"]
    # the same pair in millimetres is judged with thresholds x1000: errors scale, success does not change
    assert rows[2]["service"]["success"] == scanned["success"]
    assert_made_by_this_checkout(report["provenance"])  # which code and model, and the units of the errors
    assert "millimetres" in report["units"] and "degrees" in report["units"]


@needs_data
def test_a_pair_2_km_from_its_frames_origin_registers_over_http():
    report = real_scans.main([str(DATA), "--pairs", PAIR, "--no-fpfh", "--scales", "1",
                              "--offset", "1000", "-2000", "500"])
    assert report["offset"] == [1000.0, -2000.0, 500.0]
    scanned = report["pairs"][0]["service"]
    assert report["pairs"][0]["variant"] == "scanned" and scanned["status"] == 200 and scanned["success"], scanned


@pytest.mark.parametrize(("given", "threads"), [(None, None), ("3", 3), ("4,2", 4), ("", None), ("many", None)])
def test_fpfh_runs_on_openmps_default_threads(monkeypatch, given, threads):
    if given is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", given)
    assert real_scans.fpfh_threads() == (threads or os.cpu_count())  # unset or unreadable: one per CPU


@needs_data
def test_fpfh_half_registers_the_pair_as_scanned():
    pytest.importorskip("open3d", reason="FPFH + RANSAC + ICP needs the bench extra (Open3D)")
    case = next(c for c in real_scans.load_cases(DATA, scales=(1.0,), names=[PAIR]) if c.variant == "scanned")
    R, t = real_scans.fpfh_ransac_icp(case.source, case.target)
    assert real_scans.judged(case, R, t)["success"]


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
@needs_data
def test_compare_root_serves_another_checkout_taking_turns():
    root = Path(__file__).resolve().parents[2]  # this checkout again: the same code and models, the same poses
    report = real_scans.main([str(DATA), "--pairs", PAIR, "--no-fpfh", "--scales", "1", "--compare-root", str(root)])
    compared = report["compared"]
    assert compared["root"] == str(root) and compared["totals"]["x1"]["cases"] == 2
    for mine, theirs in zip(report["pairs"], compared["pairs"], strict=True):
        assert (mine["variant"], mine["scale"]) == (theirs["variant"], theirs["scale"])
        assert mine["service"]["success"] == theirs["service"]["success"]
        assert mine["service"]["rotation_error_deg"] == pytest.approx(theirs["service"]["rotation_error_deg"], abs=1e-3)
    mine_s, theirs_s = report["totals"]["x1"]["service_seconds"], compared["totals"]["x1"]["service_seconds"]
    assert compared["time_ratio"]["x1"] == pytest.approx(mine_s / theirs_s, rel=1e-2)


def test_compare_root_refuses_a_running_server(tmp_path, capsys):
    with pytest.raises(SystemExit):
        real_scans.main([str(tmp_path), "--no-fpfh", "--url", "http://127.0.0.1:9", "--compare-root", "."])
    assert "--compare-root serves each checkout's own bundled models" in capsys.readouterr().err


def test_near_truth_starts_are_the_angle_off_and_keep_the_centroid():
    rng = np.random.default_rng(5)
    source = rng.normal(size=(60, 3)).astype(np.float32) + 3.0
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = Rotation.from_euler("yz", [70, -20], degrees=True).as_matrix(), [0.3, -1.0, 2.0]
    cases = [real_scans.Case(f"p{i}", "cyberware-range", "scanned", 1.0, source, source, truth) for i in range(3)]
    starts = real_scans.near_truth_starts(cases, 10.0, seed=0)
    assert len(starts) == 3 and not np.allclose(starts[0], starts[1])  # a seeded axis per case
    assert all(np.array_equal(a, b) for a, b in zip(starts, real_scans.near_truth_starts(cases, 10.0, 0), strict=True))
    centre = source.mean(0, dtype=np.float64)
    for start in starts:
        degrees, _ = real_scans.pose_errors(start[:3, :3], start[:3, 3], truth)
        assert degrees == pytest.approx(10.0, abs=1e-6)
        np.testing.assert_allclose(start[:3, :3] @ centre + start[:3, 3], truth[:3, :3] @ centre + truth[:3, 3],
                                   atol=1e-9)


@pytest.mark.slow  # a benchmark's whole run: on demand (make test-all; decisions/0098)
@needs_data
def test_start_near_truth_is_sent_with_each_request():
    common = [str(DATA), "--pairs", PAIR, "--no-fpfh", "--scales", "1", "--options", '{"rotation_search": false}']
    started = real_scans.main([*common, "--start-near-truth", "10"])
    plain = real_scans.main(common)
    assert started["start_near_truth_deg"] == 10.0
    turned_started, turned_plain = (next(r["service"] for r in report["pairs"] if r["variant"] == "turned")
                                    for report in (started, plain))
    assert turned_started["success"] and not turned_plain["success"]  # turned far: only the start brings it back
    assert "search" not in turned_started["timing_ms"] and turned_started["timing_ms"]["total"] > 0


def test_start_near_truth_refuses_an_offset(tmp_path, capsys):
    with pytest.raises(SystemExit):
        real_scans.main([str(tmp_path), "--no-fpfh", "--start-near-truth", "10", "--offset", "1", "2", "3"])
    assert "--start-near-truth starts from the clouds' own frames" in capsys.readouterr().err
