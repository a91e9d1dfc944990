"""``/openapi.json`` says what the server really does: real answers of every route, 2xx and 4xx/5xx, validate against
the declared response for their status and content type; the multipart form declares the options as the server
enforces them; the README names every response field. (408, 503 and 504 bodies: ``test_api_limits.py``.)"""

from __future__ import annotations

import io
import json
import re

import numpy as np
import pytest
from api_server import LIMITED, MODEL, REPO, limited_server, pair_json, synthetic_pair
from openapi_check import assert_conforms

from service.api.schemas import RegisterOptions, RegisterResponse

CHEAP = {"iterations": 1, "refine": "none", "rotation_search": False}
FORM_CHEAP = {"iterations": "1", "refine": "none", "rotation_search": "false"}


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(array, np.float32), allow_pickle=False)
    return buf.getvalue()


@pytest.fixture(scope="module")
def doc(client) -> dict:
    return client.get("/openapi.json").json()


@pytest.fixture(scope="module")
def files():
    pair = synthetic_pair(0, keep=300)
    return {"source": ("s.npy", npy(pair.source)), "target": ("t.npy", npy(pair.target))}


def _infer_body(pair, **parameters) -> dict:
    inputs = [{"name": name, "shape": list(cloud.shape), "datatype": "FP32", "data": cloud.ravel().tolist()}
              for name, cloud in (("SOURCE", pair.source), ("TARGET", pair.target))]
    return {"inputs": inputs, "parameters": {**CHEAP, **parameters}}


def test_the_document_is_valid_openapi(doc):
    """Strict validators and client generators read it (before: a media type's ``description``, which OpenAPI 3.1
    does not allow, made openapi-spec-validator refuse the whole document)."""
    from openapi_spec_validator import validate

    validate(doc)


def test_the_headers_clients_send_and_read_are_declared(doc):
    """Every operation takes and answers ``X-Request-ID``; OIP infer declares its binary extension's header both
    ways; without ``MFGNET_API_KEY`` (the main server) the bearer token is optional."""
    for path, operations in doc["paths"].items():
        for method, operation in operations.items():
            assert "X-Request-ID" in [p["name"] for p in operation["parameters"] if p["in"] == "header"], (path, method)
            assert all("X-Request-ID" in r["headers"] for r in operation["responses"].values()), (path, method)
            if "security" in operation:
                assert operation["security"] == [{"HTTPBearer": []}, {}], (path, method)
    for path in ("/v2/models/{name}/infer", "/v2/models/{name}/versions/{version}/infer"):
        infer = doc["paths"][path]["post"]
        assert "Inference-Header-Content-Length" in [p["name"] for p in infer["parameters"]]
        assert "Inference-Header-Content-Length" in infer["responses"]["200"]["headers"]


def test_with_an_api_key_the_token_is_required(monkeypatch):
    from service.api.app import create_app

    monkeypatch.setenv("MFGNET_API_KEY", "a-key-of-sixteen-chars")
    register = create_app().openapi()["paths"]["/v1/register"]["post"]
    assert register["security"] == [{"HTTPBearer": []}]


def test_every_declared_response_content_has_a_schema(doc):
    missing = [f"{method.upper()} {path} {status} {media or '(no content)'}"
               for path, operations in doc["paths"].items() for method, operation in operations.items()
               for status, response in operation["responses"].items()
               for media, content in (response.get("content") or {"": {}}).items() if not content.get("schema")]
    assert not missing, f"responses without a schema: {missing}"


def test_real_answers_of_every_route_match_the_declared_responses(client, doc, files):
    pair = synthetic_pair(0, keep=300)
    version = client.get(f"/v2/models/{MODEL}").json()["versions"][0]
    register, batch = "/v1/register", "/v1/register/batch"
    infer, vinfer = "/v2/models/{name}/infer", "/v2/models/{name}/versions/{version}/infer"
    aligned = "/v1/register/aligned"
    eye = json.dumps(np.eye(4).tolist())
    cases = [
        ("POST", register, client.post(register, json=pair_json(pair, **CHEAP, return_iterations=True)), 200),
        ("POST", register, client.post(register, files=files, data=FORM_CHEAP), 200),
        ("POST", register, client.post(register, content=b"{", headers={"content-type": "application/json"}), 400),
        ("POST", register, client.post(register, json=pair_json(pair, model="nope")), 404),
        ("POST", register, client.post(register, content=b"x", headers={"content-type": "text/plain"}), 415),
        ("POST", register, client.post(register, json=pair_json(pair, iterations=99)), 422),
        ("POST", register, client.post(register, files=files, data={"bogus": "1"}), 422),
        ("POST", batch, client.post(batch, json={"pairs": [pair_json(pair, **CHEAP)]}), 200),
        ("POST", batch, client.post(batch, json={"pairs": []}), 422),
        ("POST", batch, client.post(batch, content=b"[", headers={"content-type": "application/json"}), 400),
        ("POST", "/v1/register/view", client.post("/v1/register/view", files=files, data=FORM_CHEAP), 200),
        ("POST", aligned, client.post(aligned, files={"source": files["source"]}, data={"transform": eye}), 200),
        ("POST", aligned, client.post(aligned, files={"source": files["source"]}), 422),
        ("GET", "/v1/models", client.get("/v1/models"), 200),
        ("GET", "/metrics", client.get("/metrics"), 200),
        ("GET", "/v2", client.get("/v2"), 200),
        ("GET", "/v2/health/live", client.get("/v2/health/live"), 200),
        ("GET", "/v2/health/ready", client.get("/v2/health/ready"), 200),
        ("GET", "/v2/models/{name}", client.get(f"/v2/models/{MODEL}"), 200),
        ("GET", "/v2/models/{name}", client.get("/v2/models/nope"), 404),
        ("GET", "/v2/models/{name}/ready", client.get(f"/v2/models/{MODEL}/ready"), 200),
        ("GET", "/v2/models/{name}/versions/{version}", client.get(f"/v2/models/{MODEL}/versions/{version}"), 200),
        ("GET", "/v2/models/{name}/versions/{version}/ready", client.get(f"/v2/models/{MODEL}/versions/0/ready"), 404),
        ("POST", infer, client.post(f"/v2/models/{MODEL}/infer", json={**_infer_body(pair), "id": "a"}), 200),
        ("POST", infer, client.post(f"/v2/models/{MODEL}/infer", json=_infer_body(pair, binary_data_output=True)),
         200),
        ("POST", infer, client.post(f"/v2/models/{MODEL}/infer", content=b"{"), 400),
        ("POST", infer, client.post("/v2/models/nope/infer", json=_infer_body(pair)), 404),
        ("POST", infer, client.post(f"/v2/models/{MODEL}/infer", content=b"{}", headers={"content-type": "text/csv"}),
         415),
        ("POST", infer, client.post(f"/v2/models/{MODEL}/infer", json={"inputs": []}), 422),
        ("POST", vinfer, client.post(f"/v2/models/{MODEL}/versions/{version}/infer", json=_infer_body(pair)), 200),
    ]
    with limited_server().client() as limited:
        key = {"Authorization": f"Bearer {LIMITED['api_key']}"}
        big = synthetic_pair(0, keep=LIMITED["max_points"] + 1)
        cases += [
            ("POST", register, limited.post(register, json=pair_json(pair, **CHEAP)), 401),
            ("POST", infer, limited.post(f"/v2/models/{MODEL}/infer", json=_infer_body(pair)), 401),
            ("POST", register, limited.post(register, json=pair_json(big, **CHEAP), headers=key), 413),
            ("POST", register, limited.post(register, files={"source": ("s.npy", npy(big.source)),
                                                             "target": files["target"]}, headers=key), 413),
            ("POST", batch, limited.post(batch, json={"pairs": [pair_json(pair)] * 3}, headers=key), 413),
        ]
    for method, path, response, status in cases:
        assert response.status_code == status, (method, path, response.status_code, response.text[:300])
        assert_conforms(doc, method, path, response)


def test_model_routes_declare_no_422_they_cannot_give(doc):
    """A string path segment is never invalid: FastAPI's automatic 422 was declared on the /v2 model routes."""
    for path, operations in doc["paths"].items():
        for method, operation in operations.items():
            if method == "get" and path.startswith("/v2/models/"):
                assert "422" not in operation["responses"], path


def test_readiness_503_declares_each_models_status(doc):
    response = doc["paths"]["/v2/health/ready"]["get"]["responses"]["503"]
    schema = doc["components"]["schemas"][response["content"]["application/json"]["schema"]["$ref"].split("/")[-1]]
    assert {"error", "ready", "models"} <= set(schema["required"])
    assert "Retry-After" in response["headers"]


def _form(doc: dict) -> dict:
    return doc["paths"]["/v1/register"]["post"]["requestBody"]["content"]["multipart/form-data"]["schema"]


def _without_null(prop: dict) -> dict:
    kinds = [kind for kind in prop.get("anyOf", []) if kind.get("type") != "null"]
    rest = {k: v for k, v in prop.items() if k not in ("anyOf", "title") and not (k == "default" and v is None)}
    return {**rest, **kinds[0]} if len(kinds) == 1 else ({**rest, "anyOf": kinds} if kinds else rest)


def test_multipart_form_declares_every_option_as_the_json_body_does(doc):
    form = _form(doc)
    options = doc["components"]["schemas"]["RegisterRequest"]["properties"]
    assert set(form["properties"]) == {"source", "target", *RegisterOptions.model_fields}
    assert form["required"] == ["source", "target"] and form["additionalProperties"] is False
    for name in ("source", "target"):
        file = form["properties"][name]
        assert file["type"] == "string" and file["format"] == "binary"
        assert all(word in file["description"] for word in ("PLY", "PCD", "LAS", ".npy", "XYZ")), name
    for name in RegisterOptions.model_fields:
        if name != "initial_transform":  # a JSON array in the body, JSON text in the form
            assert form["properties"][name] == _without_null(options[name]), name
    transform = form["properties"]["initial_transform"]
    assert transform["type"] == "string" and "src_to_tgt" in transform["description"]


def _outside(prop: dict) -> list[str]:
    """Form values just outside what ``prop`` allows."""
    values = []
    if "minimum" in prop:
        values += [str(prop["minimum"] - 1), str(prop["maximum"] + 1)]
    if "maxLength" in prop:
        values.append("m" * (prop["maxLength"] + 1))
    if "enum" in prop:
        values.append("not-" + prop["enum"][0])
    return values


def test_multipart_option_limits_are_where_the_server_refuses(client, doc, files):
    form = _form(doc)["properties"]
    limited = {name for name, prop in form.items() if _outside(prop)}
    assert limited == {"model", "iterations", "keypoints", "refine", "refine_points"}
    for name in sorted(limited):
        for value in _outside(form[name]):
            response = client.post("/v1/register", files=files, data={**FORM_CHEAP, name: value})
            assert response.status_code == 422 and name in response.json()["error"], (name, value, response.text)
    for name in ("iterations", "keypoints"):  # the declared bounds themselves are accepted
        for value in (form[name]["minimum"], form[name]["maximum"]):
            response = client.post("/v1/register", files=files, data={**FORM_CHEAP, name: str(value)})
            assert response.status_code == 200, (name, value, response.text[:300])


def test_every_example_in_the_document_is_accepted(client, doc):
    """And the request example's answer is the response example's pose, `reliable`: "Try it out" in /docs shows a
    right answer (a shift along a line of points had none)."""
    schemas = doc["components"]["schemas"]
    shown = schemas["RegisterResponse"]["examples"][0]
    for example in schemas["RegisterRequest"]["examples"]:
        response = client.post("/v1/register", json=example)
        assert response.status_code == 200, response.text[:300]
        body = response.json()
        np.testing.assert_allclose(body["euler_zyx_deg"], shown["euler_zyx_deg"], atol=0.05)  # the shown rotation
        np.testing.assert_allclose(body["translation"], shown["translation"], atol=1e-3)
        assert body["quality"]["reliable"] is True, body["warnings"]
        assert client.post("/v1/register/batch", json={"pairs": [example]}).status_code == 200
    for example in schemas["InferRequest"]["examples"]:
        assert client.post(f"/v2/models/{MODEL}/infer", json=example).status_code == 200
    found = re.findall(r'"examples?":', json.dumps(doc))
    assert len(found) == 4  # those two, RegisterResponse's (validated below), ErrorResponse.error's; add new ones here


def test_the_response_example_is_a_valid_response(doc):
    for example in doc["components"]["schemas"]["RegisterResponse"]["examples"]:
        RegisterResponse.model_validate(example)


def test_readme_names_every_response_field():
    text = (REPO / "README.md").read_text()
    paragraph = text[text.index("The response holds"):].split("\n\n", 1)[0]
    missing = [name for name in RegisterResponse.model_fields if f"`{name}`" not in paragraph]
    assert not missing, f"README's 'The response holds' paragraph does not name {missing}"
