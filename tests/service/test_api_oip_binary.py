"""OIP v2 as clients speak it: ``tritonclient.http`` with its defaults (no Content-Type, binary tensor data for
inputs and outputs) against the real server gets the ``/v1/register`` pose; hand-built binary bodies pin the
wire format down, and every framing or size mistake gets a clear 4xx."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tritonclient.http as httpclient  # the dev extra's stock OIP client
from api_server import LIMITED, MODEL, assert_error, limited_server, modelnet_pair, pair_json, synthetic_pair

INFER = f"/v2/models/{MODEL}/infer"
HEADER = "Inference-Header-Content-Length"
OUTPUTS = ("TRANSFORM", "SOURCE_INDEX", "TARGET_INDEX", "CREDIBILITY")
CHEAP = {"iterations": 1, "keypoints": 16, "refine": "none"}


@pytest.fixture(scope="module")
def triton(server):
    client = httpclient.InferenceServerClient(server.url.removeprefix("http://"), network_timeout=120)
    yield client
    client.close()


@pytest.fixture(scope="module")
def reference(client) -> dict:
    """``/v1/register`` of seeded pair 1 with the server's defaults."""
    response = client.post("/v1/register", json=pair_json(modelnet_pair(1)))
    assert response.status_code == 200, response.text
    return response.json()


def triton_inputs(pair, binary_data: bool = True) -> list:
    inputs = []
    for name, points in (("SOURCE", pair.source), ("TARGET", pair.target)):
        tensor = httpclient.InferInput(name, list(points.shape), "FP32")
        tensor.set_data_from_numpy(points.astype(np.float32), binary_data=binary_data)
        inputs.append(tensor)
    return inputs


def assert_same_pose(transform: np.ndarray, reference: dict, extent: float) -> None:
    """Rotation to 1e-6, translation to 1e-6 of the cloud's extent (the FP32 output's rounding is ~1e-7)."""
    T = np.asarray(transform, np.float64)
    np.testing.assert_allclose(T[:3, :3], np.array(reference["rotation"]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], np.array(reference["translation"]), rtol=0, atol=1e-6 * extent)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def extent(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def test_server_metadata_declares_binary_tensor_data(triton):
    assert "binary_tensor_data" in triton.get_server_metadata()["extensions"]
    assert triton.is_server_ready() and triton.is_model_ready(MODEL)
    meta = triton.get_model_metadata(MODEL)
    assert [t["name"] for t in meta["outputs"]] == list(OUTPUTS)


def test_tritonclient_defaults_get_the_v1_register_pose(triton, reference):
    pair = modelnet_pair(1)
    result = triton.infer(MODEL, triton_inputs(pair))  # defaults: binary inputs, binary_data_output
    response = result.get_response()
    for output in response["outputs"]:  # every output really came as binary data
        assert "data" not in output and output["parameters"]["binary_data_size"] > 0, output
    assert_same_pose(result.as_numpy("TRANSFORM"), reference, extent(pair.source))
    corr = reference["correspondences"]
    np.testing.assert_array_equal(result.as_numpy("SOURCE_INDEX"), [c["source_index"] for c in corr])
    np.testing.assert_array_equal(result.as_numpy("TARGET_INDEX"), [c["target_index"] for c in corr])
    np.testing.assert_array_equal(
        result.as_numpy("CREDIBILITY"), np.array([c["credibility"] for c in corr], np.float32)
    )
    assert result.as_numpy("SOURCE_INDEX").dtype == np.int64 and result.as_numpy("CREDIBILITY").dtype == np.float32
    assert response["parameters"]["inlier_ratio"] == reference["quality"]["inlier_ratio"]


def test_tritonclient_json_inputs_and_mixed_outputs(triton, reference):
    pair = modelnet_pair(1)
    outputs = [httpclient.InferRequestedOutput("TRANSFORM", binary_data=False),
               httpclient.InferRequestedOutput("SOURCE_INDEX", binary_data=True)]
    result = triton.infer(MODEL, triton_inputs(pair, binary_data=False), outputs=outputs, request_id="r-7")
    response = result.get_response()
    assert response["id"] == "r-7" and [o["name"] for o in response["outputs"]] == ["TRANSFORM", "SOURCE_INDEX"]
    assert "data" in response["outputs"][0] and "data" not in response["outputs"][1]
    assert_same_pose(result.as_numpy("TRANSFORM"), reference, extent(pair.source))
    np.testing.assert_array_equal(result.as_numpy("SOURCE_INDEX"), [c["source_index"] for c in
                                                                   reference["correspondences"]])


def test_tritonclient_passes_options_as_parameters(triton):
    result = triton.infer(MODEL, triton_inputs(modelnet_pair(1)), parameters={"iterations": 2, "keypoints": 32})
    assert result.get_response()["parameters"]["iterations"] == 2
    assert result.as_numpy("SOURCE_INDEX").shape == (32,)


# -- the wire format by hand --------------------------------------------------------------------------
def binary_body(pair, parameters: dict | None = None, outputs: list | None = None, **header) -> tuple[bytes, int]:
    """A binary-data request (JSON, then SOURCE's and TARGET's little-endian float32 bytes) and its JSON length."""
    inputs, raw = [], []
    for name, points in (("SOURCE", pair.source), ("TARGET", pair.target)):
        data = np.ascontiguousarray(points, dtype="<f4").tobytes()
        inputs.append({"name": name, "shape": list(points.shape), "datatype": "FP32",
                       "parameters": {"binary_data_size": len(data)}})
        raw.append(data)
    request = {"inputs": inputs, **({"parameters": parameters} if parameters else {}), **header}
    if outputs is not None:
        request["outputs"] = outputs
    head = json.dumps(request).encode()
    return head + b"".join(raw), len(head)


def decode_binary_response(response) -> tuple[dict, dict[str, np.ndarray]]:
    """The JSON header and every output as an array, read by the extension's rules (not by tritonclient)."""
    assert response.headers["content-type"] == "application/octet-stream"
    length = int(response.headers[HEADER])
    head = json.loads(response.content[:length])
    arrays, at = {}, length
    for output in head["outputs"]:
        dtype = {"FP32": "<f4", "INT64": "<i8"}[output["datatype"]]
        if "data" in output:
            arrays[output["name"]] = np.array(output["data"], dtype).reshape(output["shape"])
            continue
        size = output["parameters"]["binary_data_size"]
        arrays[output["name"]] = np.frombuffer(response.content[at : at + size], dtype).reshape(output["shape"])
        at += size
    assert at == len(response.content)
    return head, arrays


def test_hand_built_binary_request_equals_v1_register(client, reference):
    pair = modelnet_pair(1)
    body, length = binary_body(pair, parameters={"binary_data_output": True}, id="hand")
    response = client.post(INFER, content=body, headers={HEADER: str(length)})  # no Content-Type
    assert response.status_code == 200, response.text[:300]
    head, arrays = decode_binary_response(response)
    assert head["id"] == "hand" and [o["name"] for o in head["outputs"]] == list(OUTPUTS)
    assert_same_pose(arrays["TRANSFORM"], reference, extent(pair.source))
    assert arrays["CREDIBILITY"].shape == arrays["SOURCE_INDEX"].shape == (len(reference["correspondences"]),)


def test_output_binary_flag_overrides_the_request_default(client):
    pair = synthetic_pair(3)
    outputs = [{"name": "CREDIBILITY", "parameters": {"binary_data": False}}, {"name": "TRANSFORM"}]
    body, length = binary_body(pair, parameters={"binary_data_output": True, **CHEAP}, outputs=outputs)
    headers = {HEADER: str(length), "content-type": "application/octet-stream"}
    response = client.post(INFER, content=body, headers=headers)
    assert response.status_code == 200, response.text[:300]
    head, arrays = decode_binary_response(response)
    assert "data" in head["outputs"][0] and head["outputs"][1]["parameters"]["binary_data_size"] == 64
    assert arrays["TRANSFORM"].shape == (4, 4) and arrays["CREDIBILITY"].shape == (16,)


def test_json_without_content_type_is_json(client):
    pair = synthetic_pair(3)
    request = {"parameters": CHEAP, "inputs": [
        {"name": n, "shape": list(p.shape), "datatype": "FP32", "data": p.ravel().tolist()}
        for n, p in (("SOURCE", pair.source), ("TARGET", pair.target))]}
    response = client.post(INFER, content=json.dumps(request).encode())
    assert response.status_code == 200, response.text[:300]
    assert response.headers["content-type"] == "application/json" and HEADER not in response.headers
    assert [o["name"] for o in response.json()["outputs"]] == list(OUTPUTS) and "id" not in response.json()


# -- mistakes -----------------------------------------------------------------------------------------
def _with(body_and_length: tuple[bytes, int], change) -> tuple[bytes, int]:
    """Apply ``change(request_dict)`` to the JSON header, keeping the binary part."""
    body, length = body_and_length
    request = json.loads(body[:length])
    change(request)
    head = json.dumps(request).encode()
    return head + body[length:], len(head)


def _set(path: tuple, value):
    def change(request):
        node = request
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


PAIR = synthetic_pair(3)  # 700 points per cloud: 8400 bytes each
BASE = binary_body(PAIR, parameters=CHEAP)
SIZE = ("inputs", 0, "parameters", "binary_data_size")
CASES = {
    # name: (body, header value (None: absent), extra headers, status, words)
    "length_beyond_body": (BASE[0], str(len(BASE[0]) + 1), {}, 400, [HEADER, "body has only"]),
    "length_not_a_number": (BASE[0], "12a", {}, 400, [HEADER, "integer"]),
    "length_negative": (BASE[0], "-5", {}, 400, [HEADER, "integer"]),
    "length_zero": (BASE[0], "0", {}, 400, [HEADER, "0"]),
    "length_cuts_the_json": (BASE[0], str(BASE[1] - 3), {}, 400, ["malformed JSON"]),
    "trailing_bytes": (BASE[0] + b"\0\0\0\0", str(BASE[1]), {}, 400, ["add up to 16800 bytes", "16804"]),
    "missing_bytes": (BASE[0][:-4], str(BASE[1]), {}, 400, ["add up to 16800 bytes", "16796"]),
    "no_header": (BASE[0], None, {}, 400, [HEADER]),
    "size_not_shape": (*_with(BASE, _set(("inputs", 0, "shape"), [699, 3])), {}, 422,
                       ["SOURCE", "binary_data_size is 8400 bytes", "needs 8388"]),
    "size_not_int": (*_with(BASE, _set(SIZE, "8400")), {}, 422, ["SOURCE", "binary_data_size"]),
    "size_negative": (*_with(BASE, _set(SIZE, -1)), {}, 422, ["binary_data_size", ">= 0"]),
    "data_and_size": (*_with(BASE, _set(("inputs", 0, "data"), [0.0] * 2100)), {}, 422, ["not both"]),
    "not_fp32": (*_with(BASE, _set(("inputs", 1, "datatype"), "FP64")), {}, 422, ["TARGET", "FP32"]),
    "bad_binary_flag": (*_with(BASE, _set(("outputs",), [{"name": "TRANSFORM", "parameters": {"binary_data": 1}}])),
                        {}, 422, ["binary_data", "true or false"]),
    "bad_binary_output": (*_with(BASE, _set(("parameters", "binary_data_output"), "yes")), {}, 422,
                          ["binary_data_output"]),
    "twice_the_same_output": (*_with(BASE, _set(("outputs",), [{"name": "TRANSFORM"}, {"name": "TRANSFORM"}])),
                              {}, 422, ["TRANSFORM", "more than once"]),
    "text_plain": (BASE[0], str(BASE[1]), {"content-type": "text/plain"}, 415, ["content type", "text/plain"]),
    "gzip": (BASE[0], str(BASE[1]), {"content-encoding": "gzip"}, 415, ["content-encoding", "uncompressed"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_binary_mistakes_get_a_clear_4xx(client, case):
    body, value, extra, status, words = CASES[case]
    if case == "no_header":
        body = body[: BASE[1]]  # the JSON alone, still saying binary_data_size
    headers = {**({HEADER: str(value)} if value is not None else {}), **extra}
    assert_error(client.post(INFER, content=body, headers=headers), status, *words)


def test_nan_in_binary_data_is_named(client):
    source = PAIR.source.copy()
    source[5, 1] = np.nan
    body, length = binary_body(type(PAIR)(source, PAIR.target, PAIR.rotation, PAIR.translation), parameters=CHEAP)
    assert_error(client.post(INFER, content=body, headers={HEADER: str(length)}), 422, "SOURCE", "NaN", "row 5")


def test_still_serves_after_the_mistakes(client):
    body, length = BASE
    response = client.post(INFER, content=body, headers={HEADER: str(length)})
    assert response.status_code == 200, response.text[:300]
    assert response.headers["content-type"] == "application/json"  # no binary output asked for


def test_point_limit_is_checked_from_the_shape_before_the_data():
    """413 from the declared shape, although the binary part is far too short for it."""
    server = limited_server()
    pair = synthetic_pair(3)
    body, length = _with(binary_body(pair, parameters=CHEAP), _set(("inputs", 0, "shape"), [10**9, 3]))
    headers = {HEADER: str(length), "Authorization": f"Bearer {LIMITED['api_key']}"}
    with server.client() as limited:
        # 700 points per cloud are above this server's max_points (400): the shape says so first
        assert_error(limited.post(INFER, content=body, headers=headers), 413, "SOURCE", "1000000000",
                     "MFGNET_MAX_POINTS")



# -- the optional INITIAL_TRANSFORM input -----------------------------------------------------------
def turned_guess(pair, radians: float) -> np.ndarray:
    """``[4, 4]`` the pair's true src_to_tgt turned ``radians`` about x, rounded to float32 as the wire takes it."""
    guess = np.eye(4)
    turn = np.array([[1, 0, 0], [0, np.cos(radians), -np.sin(radians)], [0, np.sin(radians), np.cos(radians)]])
    guess[:3, :3], guess[:3, 3] = np.asarray(pair.rotation) @ turn, pair.translation
    return guess.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize("binary_data", [True, False])
def test_tritonclient_sends_an_initial_transform_as_v1_register_takes_it(client, triton, binary_data):
    """The network alone, started 1 rad off the truth: where it ends depends on the start, so the same pose as
    ``/v1/register`` with that guess, and another than without one, shows the guess arrived."""
    pair, options = modelnet_pair(2), {"refine": "none", "rotation_search": False}
    guess = turned_guess(pair, 1.0)
    with_guess = client.post("/v1/register", json=pair_json(pair, initial_transform=guess.tolist(), **options))
    without = client.post("/v1/register", json=pair_json(pair, **options))
    assert with_guess.status_code == without.status_code == 200, with_guess.text
    tensor = httpclient.InferInput("INITIAL_TRANSFORM", [4, 4], "FP32")
    tensor.set_data_from_numpy(guess.astype(np.float32), binary_data=binary_data)
    result = triton.infer(MODEL, [*triton_inputs(pair, binary_data), tensor], parameters=options)
    rotation = result.as_numpy("TRANSFORM").astype(np.float64)[:3, :3]
    np.testing.assert_allclose(rotation, np.array(with_guess.json()["rotation"]), rtol=0, atol=1e-5)
    assert np.abs(rotation - np.array(without.json()["rotation"])).max() > 1e-3


def json_infer(pair, guess: dict) -> dict:
    """A JSON infer request of ``pair`` with ``guess`` as its INITIAL_TRANSFORM input (the fields to send)."""
    inputs = [{"name": n, "shape": list(p.shape), "datatype": "FP32", "data": p.astype(np.float32).ravel().tolist()}
              for n, p in (("SOURCE", pair.source), ("TARGET", pair.target))]
    return {"inputs": [*inputs, {"name": "INITIAL_TRANSFORM", **guess}], "parameters": CHEAP}


RIGID = np.eye(4).ravel().tolist()
GUESS_CASES = {
    # name: (INITIAL_TRANSFORM fields, words of the 422)
    "shape": ({"shape": [3, 3], "datatype": "FP32", "data": RIGID[:9]}, ["INITIAL_TRANSFORM", "[4, 4]"]),
    "datatype": ({"shape": [4, 4], "datatype": "FP64", "data": RIGID}, ["INITIAL_TRANSFORM", "FP32"]),
    "count": ({"shape": [4, 4], "datatype": "FP32", "data": RIGID[:15]}, ["INITIAL_TRANSFORM", "16"]),
    "nan": ({"shape": [4, 4], "datatype": "FP32", "data": [float("nan"), *RIGID[1:]]}, ["INITIAL_TRANSFORM", "NaN"]),
    "text": ({"shape": [4, 4], "datatype": "FP32", "data": ["1", *RIGID[1:]]}, ["INITIAL_TRANSFORM", "numbers"]),
    "no_data": ({"shape": [4, 4], "datatype": "FP32"}, ["INITIAL_TRANSFORM", "data"]),
    "not_rigid": ({"shape": [4, 4], "datatype": "FP32", "data": [2.0, *RIGID[1:]]}, ["initial_transform", "rigid"]),
}


@pytest.mark.parametrize("case", sorted(GUESS_CASES))
def test_initial_transform_mistakes_get_a_clear_422(client, case):
    fields, words = GUESS_CASES[case]
    response = client.post(INFER, content=json.dumps(json_infer(PAIR, fields), allow_nan=True).encode())
    assert_error(response, 422, *words)


def test_a_binary_initial_transform_of_the_wrong_size_is_named(client):
    body, length = binary_body(PAIR, parameters=CHEAP)
    request = json.loads(body[:length])
    request["inputs"].append({"name": "INITIAL_TRANSFORM", "shape": [4, 4], "datatype": "FP32",
                              "parameters": {"binary_data_size": 60}})
    head = json.dumps(request).encode()
    response = client.post(INFER, content=head + body[length:] + bytes(60), headers={HEADER: str(len(head))})
    assert_error(response, 422, "INITIAL_TRANSFORM", "60 bytes", "64")


def test_initial_transform_as_a_parameter_is_told_to_be_the_input(client):
    request = json_infer(PAIR, {"shape": [4, 4], "datatype": "FP32", "data": RIGID})
    request["inputs"] = request["inputs"][:2]
    request["parameters"] = {**CHEAP, "initial_transform": np.eye(4).tolist()}  # /v1's option name
    assert_error(client.post(INFER, content=json.dumps(request).encode()), 422, "parameters.initial_transform",
                 "INITIAL_TRANSFORM input")
    request["parameters"]["initial_transform"] = None  # as other parameters' null: left out
    assert client.post(INFER, content=json.dumps(request).encode()).status_code == 200


def test_oip_warnings_are_one_per_line_as_v1_lists_them(client):
    """A warning's own text may hold '; ' (the separator before): the list is only recoverable line by line."""
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = PAIR.rotation, PAIR.translation
    inverted = np.linalg.inv(truth)  # a guess given target-to-source: warned, with '; ' in the warning
    v1 = client.post("/v1/register", json=pair_json(PAIR, **CHEAP, initial_transform=inverted.tolist())).json()
    oip = client.post(INFER, json=json_infer(PAIR, {"shape": [4, 4], "datatype": "FP32",
                                                    "data": inverted.astype(np.float32).ravel().tolist()})).json()
    assert any("; " in w for w in v1["warnings"]), v1["warnings"]
    assert oip["parameters"]["warnings"].split("\n") == v1["warnings"]
