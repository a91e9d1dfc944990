"""Stage guess check: a result far from the caller's ``initial_transform`` carries a warning saying how far, and
where it lies near the guess's inverse, that the guess looks given target-to-source; the pose and ``reliable`` stay.
In process, on a real-scan pair where the set is present, and over a real server with its ``/metrics`` count."""

from __future__ import annotations

import re

import numpy as np
import pytest
from api_server import pair_json, synthetic_pair
from prometheus_client.parser import text_string_to_metric_families
from real_scan_cases import GENERAL, real_case, skip_without_general
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

from service.in_process import LocalRegistrar
from service.registrar import Registrar
from service.result import RegistrationResult
from service.stages.guess_check import FAR_DEG, FAR_FROM_GUESS, FAR_SHIFT, INVERSE_DEG, pose_gap
from service.stages.pipeline import Stages

AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
HOW_FAR = re.compile(r"lies (?P<deg>[\d.]+) deg and (?P<shift>[\d.e+-]+) \(the clouds' units")
INVERTED = "initial_transform looks given target-to-source (T_source_target)"


def blob_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two samples of one asymmetric surface, the source turned 30 deg and moved: (source, target, ``[4, 4]``
    src_to_tgt truth)."""
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = Rotation.from_rotvec(np.radians(30) * AXIS).as_matrix(), [0.4, 0.3, -0.2]
    source = (asymmetric_blob(4000, seed=1) - truth[:3, 3]) @ truth[:3, :3]  # target = R @ source + t
    return source, asymmetric_blob(4000, seed=2), truth


def turned_about_centroid(T: np.ndarray, degrees: float, centroid: np.ndarray) -> np.ndarray:
    """``T [4, 4]`` after a turn of ``degrees`` about x through the source's ``centroid [3]``: a guess that far off in
    rotation and not at all where it puts the source's centroid."""
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * np.array([1.0, 0.0, 0.0])).as_matrix()
    turn[:3, 3] = centroid - turn[:3, :3] @ centroid
    return T @ turn


def far_warnings(warnings: list[str]) -> list[str]:
    return [w for w in warnings if w.startswith(FAR_FROM_GUESS + ":")]


def rotation_error_deg(result: RegistrationResult, truth: np.ndarray) -> float:
    return pose_gap(result.rotation, result.translation, truth[:3, :3], truth[:3, 3], np.zeros(3)).degrees


@pytest.fixture(scope="module")
def general() -> LocalRegistrar:
    skip_without_general()
    return LocalRegistrar("general")


def test_pose_gap_does_not_depend_on_where_the_frames_lie() -> None:
    R_a = Rotation.from_rotvec([0.0, 0.0, np.radians(10)]).as_matrix()
    centroid, far = np.array([0.2, -0.1, 0.3]), np.array([1000.0, -2000.0, 500.0])
    gap = pose_gap(R_a, np.array([0.1, 0.0, 0.0]), np.eye(3), np.zeros(3), centroid)
    # both clouds, and so both poses, in frames moved by -far (points x + far): t' = t + far - R @ far
    moved = pose_gap(R_a, np.array([0.1, 0.0, 0.0]) + far - R_a @ far, np.eye(3), np.zeros(3), centroid + far)
    assert gap.degrees == pytest.approx(10.0) and moved.degrees == pytest.approx(10.0)
    assert moved.shift == pytest.approx(gap.shift, abs=1e-9)
    assert gap.shift == pytest.approx(np.linalg.norm(R_a @ centroid + [0.1, 0, 0] - centroid))


@pytest.mark.parametrize("degrees_off", [0.0, 5.0])
def test_a_guess_near_the_truth_gives_no_warning(general, degrees_off) -> None:
    source, target, truth = blob_pair()
    guess = turned_about_centroid(truth, degrees_off, source.mean(0))
    result = general.register(source, target, initial_transform=guess)
    assert rotation_error_deg(result, truth) < 1.0
    assert far_warnings(result.warnings) == [], result.warnings


def test_a_guess_40_deg_off_is_warned_with_how_far(general) -> None:
    source, target, truth = blob_pair()
    guess = turned_about_centroid(truth, 40.0, source.mean(0))
    result = general.register(source, target, initial_transform=guess)
    assert rotation_error_deg(result, truth) < 1.0  # the right pose, not the guess
    [warning] = far_warnings(result.warnings)
    how_far = HOW_FAR.search(warning)
    gap = pose_gap(result.rotation, result.translation, guess[:3, :3], guess[:3, 3], source.mean(0))
    assert float(how_far["deg"]) == pytest.approx(gap.degrees, abs=0.05) and gap.degrees == pytest.approx(40, abs=1)
    assert float(how_far["shift"]) == pytest.approx(gap.shift, rel=1e-3)  # turned about the centroid: a small shift
    assert f"> {FAR_DEG:g} deg" in warning and f"{FAR_SHIFT:g} of the source's RMS radius" in warning
    assert INVERTED not in warning, warning


def test_the_inverse_of_the_truth_is_named_as_given_target_to_source(general) -> None:
    source, target, truth = blob_pair()
    result = general.register(source, target, initial_transform=np.linalg.inv(truth))
    assert rotation_error_deg(result, truth) < 1.0
    [warning] = far_warnings(result.warnings)
    assert INVERTED in warning and "invert it and pass T_target_source" in warning, warning
    inverse = re.search(r"within (?P<deg>[\d.]+) deg and [\d.e+-]+ of its inverse", warning)
    assert float(inverse["deg"]) <= INVERSE_DEG


def test_the_warning_changes_neither_the_pose_nor_reliable() -> None:
    skip_without_general()
    source, target, truth = blob_pair()
    unchecked = Stages(guess_check=lambda work, result, request, reference_radius: result)
    options = {"refine": "icp-plane", "rotation_search": "auto", "initial_transform": np.linalg.inv(truth)}
    checked = Registrar(GENERAL, threads=1).register(source, target, **options)
    plain = Registrar(GENERAL, threads=1, stages=unchecked).register(source, target, **options)
    np.testing.assert_array_equal(checked.transform, plain.transform)
    assert checked.reliable == plain.reliable and checked.inlier_ratio == plain.inlier_ratio
    assert [w for w in checked.warnings if w not in far_warnings(checked.warnings)] == plain.warnings
    assert len(far_warnings(checked.warnings)) == 1 and far_warnings(plain.warnings) == []


def test_an_inverted_prior_of_a_real_scan_pair_is_named() -> None:
    case = real_case("dragon_48_24", 0, "scanned")  # skips without the real-scan set
    registrar = LocalRegistrar("general")
    near = registrar.register(case.source, case.target, initial_transform=case.src_to_tgt)
    assert far_warnings(near.warnings) == [], near.warnings
    result = registrar.register(case.source, case.target, initial_transform=np.linalg.inv(case.src_to_tgt))
    assert rotation_error_deg(result, case.src_to_tgt) < 1.0
    [warning] = far_warnings(result.warnings)
    assert INVERTED in warning, warning


def far_count(client) -> float:
    """``mfgnet_registration_warnings_total`` of the kind ``FAR_FROM_GUESS``, all models (0 when absent)."""
    families = text_string_to_metric_families(client.get("/metrics").text)
    family = next(f for f in families if f.name == "mfgnet_registration_warnings")
    return sum(s.value for s in family.samples if s.name.endswith("_total") and s.labels["kind"] == FAR_FROM_GUESS)


def test_over_http_an_inverted_prior_is_named_and_counted_under_its_kind(client) -> None:
    pair = synthetic_pair(1)  # turned 28 deg
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = pair.rotation, pair.translation
    before = far_count(client)
    near = client.post("/v1/register", json=pair_json(pair, initial_transform=truth.tolist()))
    assert near.status_code == 200, near.text
    assert far_warnings(near.json()["warnings"]) == []
    response = client.post("/v1/register", json=pair_json(pair, initial_transform=np.linalg.inv(truth).tolist()))
    assert response.status_code == 200, response.text
    body = response.json()
    rotation = np.asarray(body["rotation"])
    assert np.degrees(np.arccos(np.clip((np.trace(rotation.T @ pair.rotation) - 1) / 2, -1, 1))) < 1.0
    [warning] = far_warnings(body["warnings"])
    assert INVERTED in warning, warning
    assert far_count(client) == before + 1

