"""Specification of ``POST /v1/register``, ``/v1/register/batch`` and OIP v2 ``infer`` through a real uvicorn
server: well-formed poses, valid correspondences, and exact agreement between every route and content type."""

from __future__ import annotations

import io
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from api_server import MODEL, assert_error, isolated_settings, modelnet_pair, pair_json, start_thread_server
from pydantic import ValidationError
from scipy.spatial.transform import Rotation
from shapes import ellipsoid_surface

from service.api.runner import supports_option
from service.api.schemas import InferParameters
from service.refine_modes import REFINE_MODES
from service.registrar import Registrar

CHEAP = {"iterations": 1, "keypoints": 16}


@pytest.fixture(scope="session")
def single(client):
    """``/v1/register`` results of seeded pairs 1..3, computed once (the reference for route agreement)."""
    results = {}
    for seed in (1, 2, 3):
        response = client.post("/v1/register", json=pair_json(modelnet_pair(seed)))
        assert response.status_code == 200, response.text
        results[seed] = response.json()
    return results


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    cos = (np.trace(np.asarray(R_est) @ R_true.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def test_registers_modelnet_pair_with_bounded_pose_error(single):
    pair, body = modelnet_pair(1), single[1]
    R, t, T = np.array(body["rotation"]), np.array(body["translation"]), np.array(body["transform"])
    assert R.shape == (3, 3) and t.shape == (3,) and T.shape == (4, 4)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], t)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    assert rotation_error_deg(R, pair.rotation) < 1.0  # measured 0.03 deg with the bundled clean model
    assert np.linalg.norm(t - pair.translation) < 0.01  # measured 2e-4
    assert body["model"]["name"] == MODEL and len(body["model"]["sha256"]) == 64
    assert body["iterations"] == 4
    assert body["timing_ms"]["total"] > 0 and "queue" in body["timing_ms"]
    assert set(body["quality"]) == {"inlier_ratio", "residual_rms", "reliable", "stability"}
    assert 0 <= body["quality"]["inlier_ratio"] <= 1
    assert body["quality"]["stability"] > 0.01 and body["quality"]["reliable"]  # a well-constrained pose
    assert isinstance(body["warnings"], list)
    assert "iteration_poses" not in body


def test_every_seeded_pair_registers_within_one_degree(single):
    for seed, body in single.items():
        pair = modelnet_pair(seed)
        assert rotation_error_deg(np.array(body["rotation"]), pair.rotation) < 1.0, seed
        assert np.linalg.norm(np.array(body["translation"]) - pair.translation) < 0.01, seed


def test_euler_angles_describe_the_rotation(single):
    body = single[2]
    expected = Rotation.from_matrix(np.array(body["rotation"])).as_euler("zyx", degrees=True)
    np.testing.assert_allclose(body["euler_zyx_deg"], expected, atol=1e-9)


def test_correspondences_index_the_request_arrays_with_credibility_in_unit_interval(single):
    for seed, body in single.items():
        pair = modelnet_pair(seed)
        corr = body["correspondences"]
        assert len(corr) == 128  # the model's keypoints
        src = np.array([c["source_index"] for c in corr])
        tgt = np.array([c["target_index"] for c in corr])
        cred = np.array([c["credibility"] for c in corr])
        weight = np.array([c["weight"] for c in corr])
        assert src.min() >= 0 and src.max() < len(pair.source)
        assert tgt.min() >= 0 and tgt.max() < len(pair.target)
        assert len(set(src.tolist())) == len(src)  # keypoints are distinct source points
        assert ((cred >= 0) & (cred <= 1)).all()
        assert (weight >= 0).all() and weight.sum() == pytest.approx(1.0, abs=1e-3)


def test_options_change_what_is_returned(client):
    pair = modelnet_pair(1)
    body = client.post(
        "/v1/register",
        json=pair_json(
            pair, iterations=2, keypoints=64, refine="none", return_correspondences=False, return_iterations=True
        ),
    ).json()
    assert body["iterations"] == 2
    assert "correspondences" not in body
    assert len(body["iteration_poses"]) == 2
    np.testing.assert_array_equal(body["iteration_poses"][-1]["rotation"], body["rotation"])


def test_icp_refinement_and_initial_transform_are_accepted(client):
    pair = modelnet_pair(1)
    guess = np.eye(4)
    guess[:3, :3], guess[:3, 3] = pair.rotation, pair.translation
    response = client.post("/v1/register", json=pair_json(pair, refine="icp", initial_transform=guess.tolist()))
    assert response.status_code == 200, response.text
    assert "refine" in response.json()["timing_ms"]


def test_a_pose_printed_with_three_decimals_is_a_valid_initial_transform(client):
    pair = modelnet_pair(1)
    guess = np.eye(4)
    guess[:3, :3], guess[:3, 3] = np.round(pair.rotation, 3), np.round(pair.translation, 3)  # not quite orthonormal
    response = client.post("/v1/register", json=pair_json(pair, refine="icp-plane", initial_transform=guess.tolist()))
    assert response.status_code == 200, response.text
    rotation = np.asarray(response.json()["rotation"])
    cos = (np.trace(rotation.T @ pair.rotation) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 1.0
    scaled = np.diag([1.01, 1.01, 1.01, 1.0])
    response = client.post("/v1/register", json=pair_json(pair, initial_transform=scaled.tolist()))
    assert_error(response, 422, "initial_transform must be rigid", "off by 0.0201")


@pytest.fixture(scope="session")
def plane_refined(client) -> dict:
    """``/v1/register`` of seeded pair 1 with ``refine="icp-plane"`` (the reference for the other routes)."""
    response = client.post("/v1/register", json=pair_json(modelnet_pair(1), refine="icp-plane"))
    assert response.status_code == 200, response.text
    return response.json()


def test_point_to_plane_refinement_goes_through_json(client, plane_refined):
    pair, body = modelnet_pair(1), plane_refined
    network_only = client.post("/v1/register", json=pair_json(pair, refine="none")).json()
    assert "refine" in body["timing_ms"] and "refine" not in network_only["timing_ms"]
    assert body["rotation"] != network_only["rotation"]  # the refinement ran and moved the pose
    assert rotation_error_deg(np.array(body["rotation"]), pair.rotation) < 0.01  # measured 1e-7 deg (network: 0.03)
    assert np.linalg.norm(np.array(body["translation"]) - pair.translation) < 1e-4  # measured 4e-10
    assert body["quality"]["reliable"] and not any(w.startswith("refinement") for w in body["warnings"])


def test_multistart_refinement_goes_through_json_multipart_and_oip(client, plane_refined):
    pair = modelnet_pair(1)
    body = client.post("/v1/register", json=pair_json(pair, refine="icp-plane-multistart")).json()
    assert "refine" in body["timing_ms"]
    assert rotation_error_deg(np.array(body["rotation"]), np.array(plane_refined["rotation"])) < 0.01  # right: kept
    files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
    response = client.post("/v1/register", files=files, data={"refine": "icp-plane-multistart"})
    assert response.status_code == 200, response.text
    assert response.json()["transform"] == body["transform"]
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, refine="icp-plane-multistart"))
    assert response.status_code == 200, response.text


def test_a_request_naming_no_refinement_gets_the_servers_default_icp_plane(client, plane_refined, single):
    """The server's default (MFGNET_DEFAULT_REFINE, icp-plane) applies on every route that names none."""
    assert single[1]["transform"] == plane_refined["transform"] and "refine" in single[1]["timing_ms"]
    pair = modelnet_pair(1)
    batch = client.post("/v1/register/batch", json={"pairs": [pair_json(pair)]}).json()
    assert batch["results"][0]["transform"] == plane_refined["transform"]
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair))
    np.testing.assert_array_equal(oip_transform(response), np.array(plane_refined["transform"], np.float32))


def test_the_operator_can_make_the_network_pose_alone_the_default():
    server = start_thread_server(isolated_settings(models=[MODEL], default_refine="none"))
    try:
        pair = modelnet_pair(1)
        with server.client() as client:
            default = client.post("/v1/register", json=pair_json(pair)).json()
            plane = client.post("/v1/register", json=pair_json(pair, refine="icp-plane")).json()
        assert "refine" not in default["timing_ms"] and "refine" in plane["timing_ms"]
        assert default["transform"] != plane["transform"]
    finally:
        server.stop()


def test_an_unknown_default_refinement_is_refused_at_start():
    with pytest.raises(ValidationError, match="default_refine"):
        isolated_settings(default_refine="plane")


@pytest.mark.parametrize("route", ["batch", "multipart", "oip"])
def test_point_to_plane_refinement_goes_through_every_route(client, plane_refined, route):
    pair = modelnet_pair(1)
    if route == "batch":
        response = client.post("/v1/register/batch", json={"pairs": [pair_json(pair, refine="icp-plane")]})
        assert response.status_code == 200, response.text
        assert response.json()["results"][0]["transform"] == plane_refined["transform"]
    elif route == "multipart":
        files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
        response = client.post("/v1/register", files=files, data={"refine": "icp-plane"})
        assert response.status_code == 200, response.text
        assert response.json()["transform"] == plane_refined["transform"]
    else:
        response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, refine="icp-plane"))
        assert response.status_code == 200, response.text
        transform = next(o for o in response.json()["outputs"] if o["name"] == "TRANSFORM")
        np.testing.assert_array_equal(
            np.array(transform["data"], np.float32).reshape(4, 4), np.array(plane_refined["transform"], np.float32)
        )


def test_refine_points_goes_through_every_route_and_is_range_checked(client):
    """1000-point clouds: the default refines the 768-point working clouds, ``refine_points`` all 1000."""
    pair = modelnet_pair(4, keep=1000)
    default = client.post("/v1/register", json=pair_json(pair, rotation_search=False)).json()
    body = client.post("/v1/register", json=pair_json(pair, refine_points=1000, rotation_search=False)).json()
    assert "refine" in body["timing_ms"] and body["transform"] != default["transform"]
    assert rotation_error_deg(np.array(body["rotation"]), pair.rotation) < 1.0
    files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
    form = client.post("/v1/register", files=files, data={"refine_points": "1000", "rotation_search": "false"}).json()
    assert form["transform"] == body["transform"]
    response = client.post(
        f"/v2/models/{MODEL}/infer", json=oip_request(pair, refine_points=1000, rotation_search=False)
    )
    assert response.status_code == 200, response.text
    np.testing.assert_array_equal(oip_transform(response), np.array(body["transform"], np.float32))
    for value in (16, 9000, "many"):
        assert_error(client.post("/v1/register", json=pair_json(pair, refine_points=value)), 422, "refine_points")
        response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, refine_points=value))
        assert_error(response, 422, "refine_points")
    unrefined = "refine_points sets the refinement's clouds; refine none runs no refinement"  # it was ignored
    assert_error(client.post("/v1/register", json=pair_json(pair, refine_points=1000, refine="none")), 422, unrefined)
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, refine_points=1000, refine="none"))
    assert_error(response, 422, unrefined)


def test_drop_isolated_can_be_turned_off_on_every_route(client):
    """70 points scattered around each cloud: left out by default, sampling candidates with false."""
    base, rng = modelnet_pair(5), np.random.default_rng(0)
    source, target = (
        np.concatenate([c, (c.min(0) + c.max(0)) / 2 + (c.max(0) - c.min(0)) * rng.uniform(-1, 1, (70, 3))])
        .astype(np.float32) for c in (base.source, base.target)
    )
    pair = type(base)(source, target, base.rotation, base.translation)
    default = client.post("/v1/register", json=pair_json(pair, rotation_search=False)).json()
    kept = client.post("/v1/register", json=pair_json(pair, rotation_search=False, drop_isolated=False)).json()
    first_s, first_t = len(base.source), len(base.target)  # rows from here on are the scattered points
    on_scattered = [sum(c["source_index"] >= first_s or c["target_index"] >= first_t for c in b["correspondences"])
                    for b in (default, kept)]
    assert on_scattered[0] < on_scattered[1], on_scattered
    files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
    form = client.post("/v1/register", files=files, data={"drop_isolated": "false", "rotation_search": "false"}).json()
    assert form["transform"] == kept["transform"]
    request = oip_request(pair, drop_isolated=False, rotation_search=False)
    response = client.post(f"/v2/models/{MODEL}/infer", json=request)
    np.testing.assert_array_equal(oip_transform(response), np.array(kept["transform"], np.float32))


def test_openapi_lists_every_refine_mode(client):
    doc = client.get("/openapi.json").json()
    schema = doc["components"]["schemas"]["RegisterRequest"]["properties"]["refine"]
    assert {"enum": list(REFINE_MODES), "type": "string"} in schema["anyOf"] and schema["default"] is None
    assert "icp-plane" in schema["description"] and "MFGNET_DEFAULT_REFINE" in schema["description"]
    form = doc["paths"]["/v1/register"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert form["properties"]["refine"]["enum"] == list(REFINE_MODES)
    points = doc["components"]["schemas"]["RegisterRequest"]["properties"]["refine_points"]
    assert {"type": "integer", "minimum": 32, "maximum": 8192} in points["anyOf"] and points["default"] is None
    assert form["properties"]["refine_points"]["maximum"] == 8192
    assert InferParameters.model_validate({"refine": "icp-plane"}).refine == "icp-plane"  # OIP parameters


def test_rotation_search_is_passed_through_or_refused_as_unsupported(client):
    response = client.post("/v1/register", json=pair_json(modelnet_pair(1), rotation_search=True, **CHEAP))
    if supports_option(Registrar, "rotation_search"):
        assert response.status_code == 200, response.text
    else:
        assert_error(response, 422, "rotation_search", "not supported")


def oip_transform(response) -> np.ndarray:
    """The ``TRANSFORM`` output of an OIP ``infer`` response as float32 ``[4, 4]``."""
    transform = next(o for o in response.json()["outputs"] if o["name"] == "TRANSFORM")
    return np.array(transform["data"], np.float32).reshape(4, 4)


def test_rotation_search_auto_keeps_a_good_plain_result_on_every_route(client, single):
    """Pair 1 registers well plainly (inlier ratio 0.90): "auto" returns that result and runs no search."""
    pair, reference = modelnet_pair(1), single[1]
    body = client.post("/v1/register", json=pair_json(pair, rotation_search="auto")).json()
    assert "search" not in body["timing_ms"], body
    for key in ("transform", "correspondences", "quality", "warnings"):
        assert body[key] == reference[key], key
    files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
    form = client.post("/v1/register", files=files, data={"rotation_search": "auto"}).json()
    assert form["transform"] == reference["transform"] and "search" not in form["timing_ms"]
    batch = client.post("/v1/register/batch", json={"pairs": [pair_json(pair, rotation_search="auto")]}).json()
    assert batch["results"][0]["transform"] == reference["transform"]
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, rotation_search="auto"))
    assert response.status_code == 200, response.text
    np.testing.assert_array_equal(oip_transform(response), np.array(reference["transform"], np.float32))
    assert "search_ms" not in response.json()["parameters"]
    assert response.json()["parameters"]["stability"] == reference["quality"]["stability"]


def test_rotation_search_auto_searches_after_a_poor_plain_result(client):
    """With one iteration and 16 keypoints pair 24's plain result is unreliable (inlier ratio 0.22 with `clean`
    0.2.0; pair 1's was with 0.1.0): "auto" searches."""
    pair = modelnet_pair(24)
    body = client.post("/v1/register", json=pair_json(pair, rotation_search="auto", refine="none", **CHEAP)).json()
    assert body["timing_ms"]["search"] > 0 and "search_per_hypothesis" in body["timing_ms"], body
    response = client.post(
        f"/v2/models/{MODEL}/infer", json=oip_request(pair, rotation_search="auto", refine="none", **CHEAP)
    )
    assert response.status_code == 200, response.text
    parameters = response.json()["parameters"]
    assert parameters["search_ms"] > 0 and parameters["inlier_ratio"] == body["quality"]["inlier_ratio"]
    np.testing.assert_array_equal(oip_transform(response), np.array(body["transform"], np.float32))


@pytest.mark.parametrize("value", ["maybe", "AUTO", 1])
def test_rotation_search_refuses_values_other_than_true_false_or_auto(client, value):
    pair = modelnet_pair(1)
    response = client.post("/v1/register", json=pair_json(pair, rotation_search=value))
    assert_error(response, 422, "rotation_search", "true, false or 'auto'")
    response = client.post("/v1/register/batch", json={"pairs": [pair_json(pair, rotation_search=value)]})
    assert_error(response, 422, "pairs[0].rotation_search", "'auto'")
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, rotation_search=value))
    assert_error(response, 422, "rotation_search", "'auto'")
    if isinstance(value, str):
        files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
        response = client.post("/v1/register", files=files, data={"rotation_search": value})
        assert_error(response, 422, "rotation_search", "'auto'")


def test_openapi_documents_rotation_search_auto(client):
    doc = client.get("/openapi.json").json()
    schema = doc["components"]["schemas"]["RegisterRequest"]["properties"]["rotation_search"]
    assert {"type": "boolean"} in schema["anyOf"] and any(s.get("const") == "auto" for s in schema["anyOf"])
    assert "'auto'" in schema["description"] and schema["default"] is None
    assert "MFGNET_DEFAULT_ROTATION_SEARCH" in schema["description"]
    form = doc["paths"]["/v1/register"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert {"type": "boolean"} in form["properties"]["rotation_search"]["anyOf"]
    assert any(s.get("const") == "auto" for s in form["properties"]["rotation_search"]["anyOf"])
    assert "rotation_search" in doc["paths"]["/v2/models/{name}/infer"]["post"]["description"]
    assert InferParameters.model_validate({"rotation_search": "auto"}).rotation_search == "auto"  # OIP parameters


def test_auto_is_the_default_for_refined_requests_and_the_operator_can_turn_it_off(client):
    """Pair 9 is rotated by 129 deg: plainly it ends 179 deg off; by default (MFGNET_DEFAULT_ROTATION_SEARCH auto)
    a request naming none searches and ends 0.0 deg off; ``null`` equals leaving the option out; ``false`` and
    ``refine: none`` do not search. A server whose default is off does not search."""
    pair = modelnet_pair(9, max_angle_deg=180.0)
    assert rotation_error_deg(np.eye(3), pair.rotation) > 120
    off_server = start_thread_server(isolated_settings(models=[MODEL], default_rotation_search="off"))
    try:
        with off_server.client() as off_client:
            default = off_client.post("/v1/register", json=pair_json(pair)).json()
    finally:
        off_server.stop()
    assert "search" not in default["timing_ms"]
    assert rotation_error_deg(np.array(default["rotation"]), pair.rotation) > 30
    auto_client = client  # the suite's server runs the default settings
    body = auto_client.post("/v1/register", json=pair_json(pair)).json()
    assert body["timing_ms"]["search"] > 0, body
    assert rotation_error_deg(np.array(body["rotation"]), pair.rotation) < 1.0  # measured 0.0 deg
    explicit_null = auto_client.post("/v1/register", json=pair_json(pair, rotation_search=None)).json()
    assert explicit_null["transform"] == body["transform"]
    plain = auto_client.post("/v1/register", json=pair_json(pair, rotation_search=False)).json()
    assert "search" not in plain["timing_ms"] and plain["transform"] == default["transform"]
    unrefined = auto_client.post("/v1/register", json=pair_json(pair, refine="none")).json()
    assert "search" not in unrefined["timing_ms"] and "refine" not in unrefined["timing_ms"]
    response = auto_client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair))
    assert response.status_code == 200, response.text
    assert response.json()["parameters"]["search_ms"] > 0
    np.testing.assert_array_equal(oip_transform(response), np.array(body["transform"], np.float32))


def test_an_unknown_default_rotation_search_is_refused_at_start():
    with pytest.raises(ValidationError, match="default_rotation_search"):
        isolated_settings(default_rotation_search="sometimes")


def test_multipart_npy_upload_equals_json(client, single):
    pair = modelnet_pair(1)
    files = {
        "source": ("source.npy", npy(pair.source), "application/octet-stream"),
        "target": ("target.npy", npy(pair.target.astype(np.float64)), "application/octet-stream"),
    }
    response = client.post("/v1/register", files=files, data={"return_correspondences": "true"})
    assert response.status_code == 200, response.text
    body, reference = response.json(), single[1]
    for key in ("rotation", "translation", "transform", "correspondences", "quality", "warnings", "model"):
        assert body[key] == reference[key], key


def test_multipart_options_are_form_fields(client):
    pair = modelnet_pair(1)
    files = {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}
    body = client.post(
        "/v1/register", files=files, data={"iterations": "2", "return_correspondences": "false", "model": MODEL}
    ).json()
    assert body["iterations"] == 2 and "correspondences" not in body


def oip_request(pair, nested: bool = False, **parameters) -> dict:
    def tensor(name, points):
        data = points.tolist() if nested else points.ravel().tolist()
        return {"name": name, "shape": list(points.shape), "datatype": "FP32", "data": data}

    return {
        "id": "pair-1",
        "parameters": parameters,
        "inputs": [tensor("SOURCE", pair.source), tensor("TARGET", pair.target)],
    }


@pytest.mark.parametrize("nested", [False, True])
def test_oip_infer_transform_equals_v1_register(client, single, nested):
    pair, reference = modelnet_pair(1), single[1]
    response = client.post(f"/v2/models/{MODEL}/infer", json=oip_request(pair, nested=nested))
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["model_name"] == MODEL and body["id"] == "pair-1"
    outputs = {o["name"]: o for o in body["outputs"]}
    assert set(outputs) == {"TRANSFORM", "SOURCE_INDEX", "TARGET_INDEX", "CREDIBILITY"}
    transform = outputs["TRANSFORM"]
    assert transform["datatype"] == "FP32" and transform["shape"] == [4, 4]
    np.testing.assert_array_equal(
        np.array(transform["data"], dtype=np.float32).reshape(4, 4), np.array(reference["transform"], np.float32)
    )
    corr = reference["correspondences"]
    assert outputs["SOURCE_INDEX"]["datatype"] == "INT64" and outputs["SOURCE_INDEX"]["shape"] == [len(corr)]
    assert outputs["SOURCE_INDEX"]["data"] == [c["source_index"] for c in corr]
    assert outputs["TARGET_INDEX"]["data"] == [c["target_index"] for c in corr]
    np.testing.assert_array_equal(
        np.array(outputs["CREDIBILITY"]["data"], np.float32), np.array([c["credibility"] for c in corr], np.float32)
    )


def test_oip_infer_takes_options_as_parameters_and_selects_outputs(client):
    request = oip_request(modelnet_pair(1), iterations=2, keypoints=32)
    request["inputs"][0]["shape"] = [1, *request["inputs"][0]["shape"]]  # [1, N, 3] is accepted too
    request["outputs"] = [{"name": "TRANSFORM"}, {"name": "SOURCE_INDEX"}]
    body = client.post(f"/v2/models/{MODEL}/infer", json=request).json()
    assert body["parameters"]["iterations"] == 2
    assert [o["name"] for o in body["outputs"]] == ["TRANSFORM", "SOURCE_INDEX"]
    assert body["outputs"][1]["shape"] == [32]


def test_batch_equals_single_calls(client, single):
    seeds = [1, 2, 3]
    response = client.post("/v1/register/batch", json={"pairs": [pair_json(modelnet_pair(s)) for s in seeds]})
    assert response.status_code == 200, response.text
    results = response.json()["results"]
    assert len(results) == len(seeds)
    for seed, body in zip(seeds, results, strict=True):
        for key in ("rotation", "translation", "transform", "correspondences", "quality", "warnings"):
            assert body[key] == single[seed][key], (seed, key)


def test_concurrent_requests_equal_sequential_ones(server, single):
    seeds = [1, 2, 3, 1, 2, 3]

    def post(seed):
        with server.client() as c:
            return c.post("/v1/register", json=pair_json(modelnet_pair(seed))).json()

    with ThreadPoolExecutor(len(seeds)) as pool:
        results = list(pool.map(post, seeds))
    for seed, body in zip(seeds, results, strict=True):
        assert body["transform"] == single[seed]["transform"], seed
        assert body["correspondences"] == single[seed]["correspondences"], seed


def test_a_weakly_constrained_pose_is_returned_but_not_reliable(client):
    """Two samples of a spheroid over HTTP: the pose comes back, flagged, with the free turn named."""
    source = ellipsoid_surface(np.random.default_rng(0), 800, axes=(0.6, 0.6, 1.0), bump=0.0)
    target = ellipsoid_surface(np.random.default_rng(1), 800, axes=(0.6, 0.6, 1.0), bump=0.0) + np.array([0.1, 0, 0.2])
    response = client.post("/v1/register", json={"source": source.tolist(), "target": target.tolist()})
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["quality"]["stability"] < 0.01 and body["quality"]["reliable"] is False
    assert any(w.startswith("weakly constrained: a turn about the axis") for w in body["warnings"])


def test_a_deeply_nested_initial_transform_in_a_form_is_a_422(client):
    """A form field nested past Python's recursion limit is refused like any bad JSON, never a 500."""
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(64, 3)).astype(np.float32)
    buffer = io.BytesIO()
    np.save(buffer, cloud)
    files = {"source": ("s.npy", buffer.getvalue()), "target": ("t.npy", buffer.getvalue())}
    response = client.post("/v1/register", files=files, data={"initial_transform": "[" * 30_000 + "]" * 30_000})
    assert_error(response, 422, "initial_transform")
