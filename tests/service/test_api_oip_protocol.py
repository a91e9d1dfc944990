"""OIP v2 at its edges, over HTTP against real servers: the versioned routes, outputs FP32 cannot hold, strictly
typed shapes, big integers, a binary body without its header length, an initial transform's wrong last row, CORS
for the binary extension and what the OpenAPI document says of ``infer``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tritonclient.http as httpclient  # the dev extra's stock OIP client
from api_server import MODEL, assert_error, start_subprocess_server, synthetic_pair
from tritonclient.utils import InferenceServerException

from service.api.errors import APIError

INFER = f"/v2/models/{MODEL}/infer"
HEADER = "Inference-Header-Content-Length"
CHEAP = {"iterations": 1, "keypoints": 16, "refine": "none", "rotation_search": False}
PAIR = synthetic_pair(3)
ORIGIN = "https://viewer.example"


def tensor(name: str, values, **fields) -> dict:
    values = np.asarray(values)
    return {"name": name, "shape": list(values.shape), "datatype": "FP32", "data": values.ravel().tolist(), **fields}


def infer_json(source=PAIR.source, target=PAIR.target, *extra: dict, **request) -> dict:
    return {"inputs": [tensor("SOURCE", source), tensor("TARGET", target), *extra], "parameters": CHEAP, **request}


@pytest.fixture(scope="module")
def version(client) -> str:
    versions = client.get(f"/v2/models/{MODEL}").json()["versions"]
    assert len(versions) == 1
    return versions[0]


# -- versioned routes ---------------------------------------------------------------------------------
def test_versioned_routes_serve_the_advertised_version(client, version):
    base = f"/v2/models/{MODEL}/versions/{version}"
    assert client.get(base).json() == client.get(f"/v2/models/{MODEL}").json()
    assert client.get(f"{base}/ready").json() == {"name": MODEL, "ready": True}
    response = client.post(f"{base}/infer", json=infer_json(id="v"))
    assert response.status_code == 200, response.text[:300]
    assert response.json()["model_version"] == version and response.json()["id"] == "v"


@pytest.mark.parametrize("suffix", ["", "/ready", "/infer"])
def test_another_version_is_a_404_naming_the_known_ones(client, version, suffix):
    path = f"/v2/models/{MODEL}/versions/9.9.9{suffix}"
    response = client.post(path, json=infer_json()) if suffix == "/infer" else client.get(path)
    assert_error(response, 404, "9.9.9", version)
    assert_error(client.get(f"/v2/models/no-such-model/versions/{version}"), 404, "no-such-model")


def test_tritonclient_with_a_model_version(server, version):
    client = httpclient.InferenceServerClient(server.url.removeprefix("http://"), network_timeout=120)
    try:
        assert client.is_model_ready(MODEL, model_version=version)
        assert client.get_model_metadata(MODEL, model_version=version)["versions"] == [version]
        inputs = []
        for name, points in (("SOURCE", PAIR.source), ("TARGET", PAIR.target)):
            inputs.append(httpclient.InferInput(name, list(points.shape), "FP32"))
            inputs[-1].set_data_from_numpy(points.astype(np.float32))
        result = client.infer(MODEL, inputs, model_version=version, parameters=CHEAP)
        assert result.as_numpy("TRANSFORM").shape == (4, 4)
        assert not client.is_model_ready(MODEL, model_version="9.9.9")
        with pytest.raises(InferenceServerException, match=r"9\.9\.9"):
            client.infer(MODEL, inputs, model_version="9.9.9", parameters=CHEAP)
    finally:
        client.close()


# -- Triton extensions this server does not implement ------------------------------------------------
def triton_inputs() -> list:
    inputs = []
    for name, points in (("SOURCE", PAIR.source), ("TARGET", PAIR.target)):
        inputs.append(httpclient.InferInput(name, list(points.shape), "FP32"))
        inputs[-1].set_data_from_numpy(points.astype(np.float32))
    return inputs


def shared_memory_output() -> httpclient.InferRequestedOutput:
    output = httpclient.InferRequestedOutput("TRANSFORM")
    output.set_shared_memory("transform-region", 64)  # parameters only: the region need not exist to be refused
    return output


def shared_memory_input() -> list:
    inputs = triton_inputs()
    inputs[0].set_shared_memory("source-region", PAIR.source.size * 4)
    return inputs


@pytest.mark.parametrize(
    ("inputs", "outputs", "words"),
    [
        (
            triton_inputs,
            lambda: [httpclient.InferRequestedOutput("CREDIBILITY", class_count=3)],
            ["outputs: CREDIBILITY", "classification", "not supported"],
        ),
        (
            triton_inputs,
            lambda: [shared_memory_output()],
            ["outputs: TRANSFORM", "shared_memory_region", "not supported"],
        ),
        (shared_memory_input, lambda: None, ["SOURCE", "shared_memory_region", "not supported"]),
    ],
    ids=["classification", "output-in-shared-memory", "input-in-shared-memory"],
)
def test_tritonclient_extensions_not_served_are_refused_by_name(server, inputs, outputs, words):
    """Not silently answered as plain JSON or binary data (where the client would read its shared memory region
    or expect class labels): a 422 naming the parameter, raised by tritonclient with the server's message."""
    client = httpclient.InferenceServerClient(server.url.removeprefix("http://"), network_timeout=120)
    try:
        with pytest.raises(InferenceServerException) as raised:
            client.infer(MODEL, inputs(), outputs=outputs(), parameters=CHEAP)
        assert raised.value.status() == "422", raised.value
        for word in words:
            assert word in raised.value.message(), raised.value.message()
    finally:
        client.close()


# -- outputs FP32 cannot hold -------------------------------------------------------------------------
FAR = np.random.default_rng(0).normal(size=(64, 3))  # the clouds 6e38 apart: each fits FP32, their offset does not


@pytest.mark.parametrize("binary", [False, True])
def test_a_translation_beyond_fp32_is_a_422_not_a_500(client, binary):
    request = infer_json(FAR + 3e38, FAR - 3e38, outputs=[{"name": "TRANSFORM", "parameters": {"binary_data": binary}}])
    assert_error(client.post(INFER, json=request), 422, "TRANSFORM's translation", "beyond the FP32 range",
                 "/v1/register")


def test_outputs_not_asked_for_are_not_checked(client):
    response = client.post(INFER, json=infer_json(FAR + 3e38, FAR - 3e38, outputs=[{"name": "SOURCE_INDEX"}]))
    assert response.status_code == 200, response.text[:300]


def test_every_fp32_output_is_checked_alike():
    from service.api.oip_response import fp32_wire  # here: the module's other tests run without it
    with pytest.raises(APIError, match="CREDIBILITY is beyond the FP32 range"):
        fp32_wire("CREDIBILITY", np.array([0.5, 1e39]))
    with pytest.raises(APIError, match=r"^TRANSFORM is beyond"):  # not only the translation
        fp32_wire("TRANSFORM", np.eye(4) * 1e39)
    with pytest.raises(ValueError, match="does not allow"):  # NaN: a bug of ours, still a 500
        fp32_wire("CREDIBILITY", np.array([np.nan]))


# -- strict shapes and big integers -------------------------------------------------------------------
@pytest.mark.parametrize(("shape", "index"), [([len(PAIR.source), "3"], 1), ([float(len(PAIR.source)), 3], 0),
                                              ([len(PAIR.source), True], 1)], ids=["text", "float", "bool"])
def test_shapes_must_be_integers(client, shape, index):
    request = infer_json()
    request["inputs"][0]["shape"] = shape
    assert_error(client.post(INFER, json=request), 422, f"inputs[0].shape[{index}]", "integer")


def test_integers_of_2_to_the_64_and_more_are_numbers_fp32_holds(client):
    source = (PAIR.source.astype(np.float64) + 10) * 2.0**64  # the pair scaled, far from the origin
    as_ints = infer_json(source, (PAIR.target.astype(np.float64) + 10) * 2.0**64)
    as_ints["inputs"][0]["data"] = [int(v) for v in source.ravel()]  # JSON integers of 2**64 and more
    assert min(as_ints["inputs"][0]["data"]) >= 2**64
    response = client.post(INFER, content=json.dumps(as_ints).encode())
    assert response.status_code == 200, response.text[:300]


@pytest.mark.parametrize("big", [2**130, 10**400], ids=["2**130", "10**400"])
def test_integers_beyond_fp32_are_named(client, big):
    request = infer_json()
    request["inputs"][1]["data"][7] = big
    assert_error(client.post(INFER, content=json.dumps(request).encode()), 422, "TARGET", "beyond the FP32 range")


@pytest.mark.parametrize("nesting", ["columns", "deeper"])
def test_data_nested_otherwise_than_its_shape_is_named(client, nesting):
    """A [3, N] nesting declared [N, 3] registered 46 deg off, and lists nested deeper than the shape turned a true
    into 1.0: nested data must follow the shape (flat data stays row-major)."""
    request = infer_json()
    source = PAIR.source.astype(np.float64)
    if nesting == "columns":
        request["inputs"][0]["data"] = source.T.tolist()  # [3, N]
    else:
        request["inputs"][0]["data"] = [[[[[float(v)] for v in row]] for row in source.tolist()]]  # [1, N, 1, 3, 1]
        request["inputs"][0]["data"][0][5][0][1] = [True]
    nested = "[3, " if nesting == "columns" else "[1, "
    assert_error(client.post(INFER, content=json.dumps(request).encode()), 422, "SOURCE", "nested as " + nested,
                 "flat")


# -- a binary body without its header length ----------------------------------------------------------
def binary_request(**parameters) -> tuple[bytes, int]:
    """A body of JSON and then SOURCE's and TARGET's float32 bytes, and the JSON's length."""
    inputs, raw = [], b""
    for name, points in (("SOURCE", PAIR.source), ("TARGET", PAIR.target)):
        data = np.ascontiguousarray(points, "<f4").tobytes()
        inputs.append({"name": name, "shape": list(points.shape), "datatype": "FP32",
                       "parameters": {"binary_data_size": len(data)}})
        raw += data
    head = json.dumps({"inputs": inputs, "parameters": {**CHEAP, **parameters}}).encode()
    return head + raw, len(head)


@pytest.mark.parametrize("content_type", [None, "application/octet-stream"])
def test_binary_data_without_the_header_length_names_the_header(client, content_type):
    headers = {"content-type": content_type} if content_type else {}
    assert_error(client.post(INFER, content=binary_request()[0], headers=headers), 400, "malformed JSON", HEADER)


def test_json_then_text_without_the_header_length_names_the_header(client):
    body = json.dumps(infer_json()).encode() + b"\0\0\0\0"  # zero floats: valid UTF-8 after the JSON
    assert_error(client.post(INFER, content=body), 400, "malformed JSON", HEADER)


def test_plain_malformed_json_gets_no_header_hint(client):
    response = client.post(INFER, content=b'{"inputs": [1, 2,', headers={"content-type": "application/json"})
    assert HEADER not in assert_error(response, 400, "malformed JSON")["error"]


# -- INITIAL_TRANSFORM --------------------------------------------------------------------------------
def test_an_initial_transform_with_a_wrong_last_row_is_told_so(client):
    guess = np.eye(4)
    guess[3] = [1, 2, 3, 4]
    response = client.post(INFER, json=infer_json(PAIR.source, PAIR.target, tensor("INITIAL_TRANSFORM", guess)))
    body = assert_error(response, 422, "last row", "0 0 0 1", "1 2 3 4")
    assert "off by" not in body["error"]
    assert "INITIAL_TRANSFORM must be rigid" in body["error"]  # the input's name, as every other OIP 422 gives it


@pytest.mark.parametrize("which", ["SOURCE", "TARGET"])
def test_a_cloud_of_too_few_points_is_named_as_its_input(client, which):
    clouds = {"SOURCE": PAIR.source, "TARGET": PAIR.target}
    clouds[which] = clouds[which][:2]
    body = assert_error(client.post(INFER, json=infer_json(clouds["SOURCE"], clouds["TARGET"])), 422, "at least")
    assert f"{which}: needs at least" in body["error"]


# -- CORS ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cors_server():
    server = start_subprocess_server("cors", MFGNET_CORS_ORIGINS=ORIGIN)
    yield server
    server.stop()


def test_cors_allows_and_exposes_the_binary_extensions_header(cors_server):
    with cors_server.client() as c:
        preflight = c.options(INFER, headers={"Origin": ORIGIN, "Access-Control-Request-Method": "POST",
                                              "Access-Control-Request-Headers": f"content-type, {HEADER.lower()}"})
        assert preflight.status_code == 200, preflight.text
        assert HEADER.lower() in preflight.headers["access-control-allow-headers"].lower()
        body, length = binary_request(binary_data_output=True)
        response = c.post(INFER, content=body, headers={"Origin": ORIGIN, HEADER: str(length)})
        assert response.status_code == 200, response.text[:300]
        assert HEADER.lower() in response.headers["access-control-expose-headers"].lower()
        assert "content-disposition" in response.headers["access-control-expose-headers"].lower()  # aligned names
        assert response.headers["access-control-allow-origin"] == ORIGIN


def test_a_refused_preflight_is_a_json_error(cors_server):
    with cors_server.client() as c:
        refused = c.options(INFER, headers={"Origin": ORIGIN, "Access-Control-Request-Method": "POST",
                                            "Access-Control-Request-Headers": "x-not-allowed"})
        assert_error(refused, 400, "CORS", "headers")


# -- OpenAPI ------------------------------------------------------------------------------------------
def test_openapi_says_what_infer_takes_and_returns(client):
    schema = client.get("/openapi.json").json()
    for path in (INFER.replace(MODEL, "{name}"), "/v2/models/{name}/versions/{version}/infer"):
        ok = schema["paths"][path]["post"]["responses"]["200"]
        assert set(ok["content"]) == {"application/json", "application/octet-stream"}, path
    components = schema["components"]["schemas"]
    assert {"drop_isolated", "binary_data_output"} <= set(components["InferRequest"]["description"].replace(",", " ")
                                                           .split())
    assert "INITIAL_TRANSFORM" in components["ModelMetadata"]["properties"]["inputs"]["description"]
    assert "INITIAL_TRANSFORM" in components["InferInputTensor"]["properties"]["name"]["description"]
    assert "INITIAL_TRANSFORM" in components["TensorMetadata"]["properties"]["name"]["description"]
