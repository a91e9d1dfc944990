"""bench.turntable_scans: simulated turntable range scans of other objects, registered and judged as the dragon's."""

from __future__ import annotations

import json

import numpy as np
import pytest
from provenance_check import assert_made_by_this_checkout
from scipy.spatial import cKDTree

from bench.failures import CLASSES
from bench.turntable_scans import RADIUS, Shape, about_up, main, turntable_pairs
from model.analytic_shapes import lumpy_sphere
from model.data import data_dir
from model.sensor_sim import estimate_normals
from service.free_space import range_view

needs_data = pytest.mark.skipif(not (data_dir() / "modelnet40_test.npz").exists(),
                                reason="ModelNet40 absent (../shared/data/modelnet40 or $MFGNET_DATA)")


def test_the_ground_truth_turns_the_scan_back_onto_the_scan_at_0_deg() -> None:
    points = lumpy_sphere(30_000, seed=1)
    pairs = turntable_pairs(Shape("lumpy", "lumpy_sphere", points, estimate_normals(points)), [24.0, 48.0])
    assert [p.name for p in pairs] == ["lumpy_24_0", "lumpy_48_0"]
    for pair, angle in zip(pairs, (24.0, 48.0), strict=True):
        assert pair.sensor == "cyberware-range"
        assert 0.9 * RADIUS < np.linalg.norm(pair.target, axis=1).max() < 1.1 * RADIUS  # metres, centred
        tree = cKDTree(pair.target)
        T = pair.src_to_tgt
        right = np.median(tree.query(pair.source @ T[:3, :3].T + T[:3, 3])[0])
        wrong_way = np.median(tree.query(pair.source @ about_up(angle).T)[0])  # the table turned on, not back
        assert right < 0.001  # metres: noise and sampling only
        assert right < wrong_way / 3


def test_the_scans_are_range_images_on_a_pixel_grid_as_the_service_reads_them() -> None:
    """Evenly spaced returns (random thinning left a tenth of the points at under half the median spacing) whose
    density follows the viewing direction: the free-space stage reads each as a range image."""
    points = lumpy_sphere(30_000, seed=1)
    pair = turntable_pairs(Shape("lumpy", "lumpy_sphere", points, estimate_normals(points)), [24.0])[0]
    for scan in (pair.source, pair.target):
        spacing = cKDTree(scan).query(scan, 2)[0][:, 1]  # [N]
        assert np.quantile(spacing, 0.1) > 0.8 * np.median(spacing)
        assert range_view(scan.astype(np.float64)) is not None


@needs_data
def test_a_tiny_run_judges_classes_and_writes_every_case(tmp_path) -> None:
    out = tmp_path / "turntable.json"
    report = main(["--shapes", "cup", "--count", "1", "--turns", "1", "--no-fpfh", "--json", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    names = [(row["pair"].split("_")[0], row["pair"].split("_")[-2], row["variant"]) for row in report["rows"]]
    assert names == [
        ("cup", "24", "scanned"),
        ("cup", "24", "turned"),
        ("cup", "48", "scanned"),
        ("cup", "48", "turned"),
    ]
    for row in report["rows"]:
        assert (row["kind"], row["class"]) == ("solids of revolution", "cup")
        service = row["service"]
        right = service["rotation_error_deg"] < 5 and service["translation_error"] < 0.01
        assert service["success"] == right
        assert ("failure" in service) == (not right)
        assert service.get("failure", CLASSES[0]) in CLASSES
        assert "fpfh" not in row
    totals = report["totals"]
    assert list(totals["kinds"]) == ["solids of revolution"] and list(totals["classes"]) == ["cup"]
    assert totals["all"]["cases"] == totals["kinds"]["solids of revolution"]["cases"] == 4
    assert totals["all"]["service_successes"] == sum(row["service"]["success"] for row in report["rows"])
    assert sum(totals["all"]["failures"].values()) == 4 - totals["all"]["service_successes"]
    assert assert_made_by_this_checkout(report["provenance"])


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--shapes", "lumpy_sphere", "--angles", "360"], "below 360"),
        (["--shapes", "lumpy_sphere", "--angles", "24", "24"], "given twice"),
        (["--shapes", "lumpy_sphere", "lumpy_sphere"], "given twice"),
    ],
)
def test_bad_options_are_usage_errors(argv, message, capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        main([*argv, "--no-fpfh"])
    assert stopped.value.code == 2
    assert message in capsys.readouterr().err


@needs_data
def test_an_unknown_shape_is_a_usage_error_naming_what_is_there(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["--shapes", "teapot", "--no-fpfh"])
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "teapot" in err and "lumpy_sphere" in err and "person" in err
