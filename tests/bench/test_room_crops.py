"""Pairs cut from one room fragment: the windows overlap as asked, the two clouds share no point, the truth puts the
source back on the target, and the service registers a case started from its truth."""

from __future__ import annotations

import numpy as np
import pytest

from bench.real_scans import data_dir, pose_errors
from bench.room_crops import cases, fragments, main, windows
from bench.variant_runs import general_registrar
from service.kdtree import KDTree

FRAGMENT = "3dm_hotel3_15_8/source"

needs_set = pytest.mark.skipif(
    not (data_dir() / "3dm_hotel3_15_8.npz").exists(),
    reason=f"real-scan set absent ({data_dir()}; set MFGNET_REAL_DATA)",
)


@needs_set
def test_every_indoor_cloud_once_and_no_other():
    names = [name for name, _, _ in fragments(data_dir())]
    assert len(names) == len(set(names)) and FRAGMENT in names
    assert all(name.split("/")[0].startswith(("3dm_", "3dlo_")) for name in names)  # no dragon, no LiDAR


@needs_set
@pytest.mark.parametrize("overlap", [0.3, 0.7])
def test_the_windows_overlap_by_the_share_asked(overlap: float):
    ((_, _, points),) = fragments(data_dir(), [FRAGMENT])
    a, b = windows(points, overlap, np.random.default_rng(3))
    assert len(a) == len(b)
    assert abs(len(np.intersect1d(a, b)) / len(a) - overlap) < 0.002
    assert len(np.union1d(a, b)) == len(points)  # between them, the whole fragment


@needs_set
def test_the_truth_puts_the_source_back_and_the_clouds_share_no_point():
    first = list(cases(data_dir(), 0.5, turns=1, names=[FRAGMENT]))
    again = list(cases(data_dir(), 0.5, turns=1, names=[FRAGMENT]))
    assert [c[0] for c in first] == [f"{FRAGMENT}/o50/cut", f"{FRAGMENT}/o50/turned"]
    for one, two in zip(first, again, strict=True):  # seeded
        assert all(np.array_equal(x, y) for x, y in zip(one[2:], two[2:], strict=True))
    (_, sensor, src, tgt, truth), (_, _, src_t, _, truth_t) = first
    assert sensor.startswith(("kinect-", "xtion-"))
    back = src.astype(np.float64) @ truth[:3, :3].T + truth[:3, 3]  # [N, 3] in the target's frame
    distance = KDTree(tgt).query(back, k=1)[0].ravel()
    assert 0.45 < (distance < 0.025).mean() < 0.6  # half the source lies on the target, within a voxel
    # resampled apart: no source point lands on one of the target's (float32 rounding leaves ~1e-6 m), and where they
    # overlap they lie a few millimetres apart, not on the same samples
    assert distance.min() > 1e-5 and np.median(distance[distance < 0.025]) > 0.002
    moved = back, src_t.astype(np.float64) @ truth_t[:3, :3].T + truth_t[:3, 3]
    assert np.abs(moved[0] - moved[1]).max() < 1e-4  # the turned case lands on the same points
    assert pose_errors(truth[:3, :3], truth[:3, 3], np.eye(4))[0] > 4.0  # as cut, the source is moved


@needs_set
def test_started_at_its_truth_the_service_stays_there():
    _, _, src, tgt, truth = next(cases(data_dir(), 0.7, turns=1, names=[FRAGMENT]))  # as cut
    result = general_registrar().register(src, tgt, refine="icp-plane", rotation_search=False, initial_transform=truth)
    degrees, error = pose_errors(result.rotation, result.translation, truth)
    assert degrees < 1.0 and error < 0.03


@needs_set
def test_the_run_totals_its_rows(tmp_path):
    out = tmp_path / "crops.json"
    report = main(["--fragments", FRAGMENT, "--overlaps", "0.7", "--turns", "1", "--no-fpfh", "--json", str(out)])
    rows = report["rows"]
    assert [r["variant"] for r in rows] == [f"{FRAGMENT}/o70/cut", f"{FRAGMENT}/o70/turned"]
    figures = report["totals"]["o70"]
    assert figures == report["totals_all"] == report["by_fragment"][FRAGMENT]
    assert figures["cases"] == 2 and figures["service_successes"] == sum(r["service_success"] for r in rows)
    assert "fpfh_success" not in rows[0]
    assert all(0.0 <= r["inlier_ratio"] <= 1.0 and isinstance(r["warnings"], list) for r in rows)  # what prose cites
    assert out.read_text().count('"variant"') == 2


def _usage_error(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    with pytest.raises(SystemExit) as ended:
        main(argv)
    assert ended.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_usage_errors_exit_2_before_any_work(tmp_path, capsys):
    assert "between 0 and 1" in _usage_error(["--overlaps", "1.2", "--no-fpfh"], capsys)
    cloud = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    np.savez(tmp_path / "far.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="lidar")
    assert "no indoor pair" in _usage_error([str(tmp_path), "--no-fpfh"], capsys)


@needs_set
def test_unknown_fragment_and_json_folder_are_usage_errors(tmp_path, capsys):
    assert "--fragments: no indoor cloud nope" in _usage_error(["--fragments", "nope", "--no-fpfh"], capsys)
    assert "does not exist" in _usage_error(["--json", str(tmp_path / "no" / "r.json"), "--no-fpfh"], capsys)
