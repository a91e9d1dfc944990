"""``mfgnet register --rotation-search`` recovers a relative rotation far outside the trained range."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import bumpy_ellipsoid
from typer.testing import CliRunner

from service.cli import app
from service.manifest import bundled_models_dir
from service.pointcloud_io import write_points

pytestmark = pytest.mark.skipif(not (bundled_models_dir() / "clean" / "manifest.json").exists(),
                                reason="bundled model 'clean' absent")


def test_register_with_rotation_search_recovers_150_degrees(tmp_path):
    src = bumpy_ellipsoid(800)
    R_true = Rotation.from_euler("z", 150, degrees=True).as_matrix()
    write_points(tmp_path / "a.npy", src)
    write_points(tmp_path / "b.npy", src @ R_true.T + [0.2, 0.0, -0.1])
    result = CliRunner().invoke(
        app, ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--rotation-search", "--refine", "icp",
              "--json"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    R = np.asarray(record["rotation"])
    error_deg = np.degrees(2 * np.arcsin(min(1.0, np.linalg.norm(R - R_true) / (2 * np.sqrt(2)))))
    assert error_deg < 2.0 and "search" in record["timing_ms"]


def rotation_error_deg(record: dict, R_true: np.ndarray) -> float:
    R = np.asarray(record["rotation"])
    return float(np.degrees(2 * np.arcsin(min(1.0, np.linalg.norm(R - R_true) / (2 * np.sqrt(2))))))


def register_json(tmp_path, degrees: float, *options: str):
    src = bumpy_ellipsoid(800)
    R_true = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    write_points(tmp_path / "a.npy", src)
    write_points(tmp_path / "b.npy", src @ R_true.T + [0.2, 0.0, -0.1])
    result = CliRunner().invoke(app, ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), *options, "--json"])
    return result, R_true


def test_rotation_search_mode_auto_searches_a_150_degree_pair(tmp_path):
    result, R_true = register_json(tmp_path, 150, "--rotation-search-mode", "auto", "--refine", "icp")
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert rotation_error_deg(record, R_true) < 2.0 and "search" in record["timing_ms"]


def test_rotation_search_mode_auto_keeps_an_easy_plain_result(tmp_path):
    plain, R_true = register_json(tmp_path, 20, "--refine", "icp")
    auto, _ = register_json(tmp_path, 20, "--refine", "icp", "--rotation-search-mode", "auto")
    assert plain.exit_code == 0 and auto.exit_code == 0, (plain.output, auto.output)
    plain_record, auto_record = json.loads(plain.stdout), json.loads(auto.stdout)
    assert "search" not in auto_record["timing_ms"] and rotation_error_deg(auto_record, R_true) < 1.0
    assert auto_record["transform"] == plain_record["transform"]


@pytest.mark.parametrize(("options", "words"), [
    (["--rotation-search-mode", "maybe"], ["maybe", "off", "auto"]),
    (["--rotation-search", "--rotation-search-mode", "auto"], ["contradicts", "--rotation-search-mode auto"]),
    (["--no-rotation-search", "--rotation-search-mode", "on"], ["contradicts"]),
])
def test_rotation_search_mode_usage_errors_exit_2(tmp_path, options, words):
    result = CliRunner().invoke(app, ["register", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), *options])
    assert result.exit_code == 2, result.output
    for word in words:
        assert word in result.output, result.output


def test_rotation_search_options_map_to_the_registrar_argument():
    from service.search_mode import RotationSearchMode, rotation_search_from_options

    assert rotation_search_from_options(None, None) is None  # not given: the caller's default
    assert rotation_search_from_options(True, None) is True and rotation_search_from_options(False, None) is False
    assert rotation_search_from_options(None, RotationSearchMode.auto) == "auto"
    assert rotation_search_from_options(True, RotationSearchMode.on) is True
    assert rotation_search_from_options(False, "off") is False


def test_the_services_default_search_applies_only_to_refined_requests():
    from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH, service_rotation_search

    assert SERVICE_DEFAULT_ROTATION_SEARCH == "auto"  # clouds at any relative orientation (decision 0007)
    assert service_rotation_search(None, "icp-plane") == "auto"
    assert service_rotation_search(None, "icp-plane", "off") is False
    assert service_rotation_search(None, "icp-plane", "auto") == "auto"
    assert service_rotation_search(None, "icp", "auto") == "auto"
    assert service_rotation_search(None, "none", "auto") is False  # unrefined poses never fit tightly: no search
    assert service_rotation_search(None, "icp-plane", "on") is True
    for requested in (False, True, "auto"):  # the request's own choice wins, refined or not
        assert service_rotation_search(requested, "none") == requested
        assert service_rotation_search(requested, "icp-plane", "off") == requested
