"""Stage scale check: clouds whose sizes differ as units do (millimetres against metres) carry a warning naming both
sizes; clouds of one unit do not; the pose and ``reliable`` stay. In process, on the set's pairs where they are
present, and over a real server with its ``/metrics`` count."""

from __future__ import annotations

import re

import numpy as np
import pytest
from api_server import pair_json, synthetic_pair
from prometheus_client.parser import text_string_to_metric_families
from real_scan_cases import GENERAL, skip_without_general
from shapes import asymmetric_blob

from service.normalization import rms_radius
from service.registrar import Registrar
from service.stages.pipeline import Stages
from service.stages.scale_check import SIZE_MISMATCH, UNITS_RATIO, size_mismatch

RATIO = re.compile(r"RMS radius is (?P<ratio>\d+)x the (?P<smaller>source|target)'s \((?P<larger_size>[\d.e+-]+) "
                   r"against (?P<smaller_size>[\d.e+-]+)\)")


def mismatched(warnings: list[str]) -> list[str]:
    return [w for w in warnings if w.startswith(f"{SIZE_MISMATCH}:")]


@pytest.fixture(scope="module")
def general() -> Registrar:
    skip_without_general()
    return Registrar(GENERAL, threads=1)


def test_rms_radius_is_the_rms_distance_from_the_centroid() -> None:
    points = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 3.0, 0], [0, -3.0, 0]]) + np.array([5.0, -2.0, 7.0])
    assert rms_radius(points) == pytest.approx(np.sqrt((1 + 1 + 9 + 9) / 4))


@pytest.mark.parametrize(("scale", "larger"), [(1000.0, "source"), (0.01, "target"), (1 / 39.37, "target")])
def test_a_source_in_other_units_is_warned_with_both_sizes(general, scale, larger) -> None:
    """Millimetres, centimetres or inches against metres: one warning, first (the poor fit and low overlap it causes
    after it), naming the larger cloud and the ratio."""
    source, target = asymmetric_blob(3000, seed=1), asymmetric_blob(3000, seed=2)
    result = general.register(source * scale, target, refine="icp-plane", rotation_search="auto")
    [warning] = mismatched(result.warnings)
    assert result.warnings[0] == warning and len(result.warnings) > 1, result.warnings
    found = RATIO.search(warning)
    ratio = max(scale, 1 / scale)
    assert float(found["ratio"]) == pytest.approx(ratio, rel=0.05), warning
    assert warning.startswith(f"{SIZE_MISMATCH}: the {larger}'s") and "different units" in warning
    assert float(found["larger_size"]) / float(found["smaller_size"]) == pytest.approx(ratio, rel=0.05)  # in order


@pytest.mark.parametrize(("source_scale", "target_scale"), [(1.0, 1.0), (1000.0, 1000.0), (20.0, 1.0)])
def test_clouds_of_one_unit_are_not_warned(general, source_scale, target_scale) -> None:
    """Both clouds in any one unit, and a source 20 times the target's size (a map against a scan of it), pass."""
    source = asymmetric_blob(3000, seed=1) * source_scale
    target = asymmetric_blob(3000, seed=2) * target_scale
    assert mismatched(general.register(source, target, refine="icp-plane").warnings) == []


def test_a_cloud_of_one_repeated_point_is_not_compared(general) -> None:
    """Its RMS radius is the centroid's rounding (~1e-15): the degenerate-cloud warning says what is wrong, not a size
    mismatch of 1e14x (it was counted among the size mismatches)."""
    target = asymmetric_blob(200, seed=2)
    result = general.register(np.tile([[1.0, 2.0, 3.0]], (100, 1)), target, refine="icp-plane")
    assert mismatched(result.warnings) == [] and any("identical" in w for w in result.warnings), result.warnings


@pytest.mark.parametrize("scale", [1e-12, 1e12])
def test_a_cloud_of_another_size_by_far_is_still_compared(general, scale) -> None:
    """A shaped cloud 1e12 times smaller or larger is no repeated point: it was taken for one past 1e9x, unwarned."""
    source, target = asymmetric_blob(500, seed=1) * scale, asymmetric_blob(500, seed=2)
    warnings = general.register(source, target, refine="none").warnings
    assert len(mismatched(warnings)) == 1 and not any("identical" in w for w in warnings), warnings


def test_the_threshold_lies_between_the_sizes_of_one_scene_and_units() -> None:
    assert size_mismatch(UNITS_RATIO * 2.0, 2.0).startswith(f"{SIZE_MISMATCH}: the source's RMS radius is 30x")
    assert UNITS_RATIO <= 39.37 / 1.2  # inches against metres is caught, with the set's spread of sizes (1.2x)


def test_the_warning_changes_neither_the_pose_nor_reliable() -> None:
    skip_without_general()
    source, target = asymmetric_blob(3000, seed=1) * 1000.0, asymmetric_blob(3000, seed=2)
    unchecked = Stages(scale_check=lambda work, result: result)
    checked = Registrar(GENERAL, threads=1).register(source, target, refine="icp-plane", rotation_search="auto")
    plain = Registrar(GENERAL, threads=1, stages=unchecked).register(source, target, refine="icp-plane",
                                                                      rotation_search="auto")
    np.testing.assert_array_equal(checked.transform, plain.transform)
    assert checked.reliable == plain.reliable is False
    assert [w for w in checked.warnings if w not in mismatched(checked.warnings)] == plain.warnings
    assert len(mismatched(checked.warnings)) == 1 and mismatched(plain.warnings) == []


def mismatch_count(client) -> float:
    families = text_string_to_metric_families(client.get("/metrics").text)
    family = next(f for f in families if f.name == "mfgnet_registration_warnings")
    return sum(s.value for s in family.samples if s.name.endswith("_total") and s.labels["kind"] == SIZE_MISMATCH)


def test_over_http_a_source_in_millimetres_is_warned_and_counted_under_its_kind(client) -> None:
    pair = synthetic_pair(1)
    before = mismatch_count(client)
    same = client.post("/v1/register", json=pair_json(pair))
    assert same.status_code == 200, same.text
    assert mismatched(same.json()["warnings"]) == []
    body = pair_json(pair)
    body["source"] = (np.asarray(body["source"]) * 1000.0).tolist()
    response = client.post("/v1/register", json=body)
    assert response.status_code == 200, response.text
    [warning] = mismatched(response.json()["warnings"])
    assert float(RATIO.search(warning)["ratio"]) == pytest.approx(1000, rel=0.05), warning  # two samples of one shape
    assert mismatch_count(client) == before + 1
