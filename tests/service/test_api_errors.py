"""Every bad request gets a JSON ``{"error": ...}`` with the right status (never 500, never a traceback
or a server path), and the server still answers a valid request correctly afterwards. The requests are built
from a generated shape (``api_server.synthetic_pair``): the battery runs without the ModelNet40 files."""

from __future__ import annotations

import io
import json
import pickle

import numpy as np
import pytest
from api_server import MODEL, assert_error, pair_json, synthetic_pair

SEED = 3


CHEAP = {"iterations": 1, "keypoints": 16}  # a quick valid request for the after-check


@pytest.fixture(scope="session")
def reference(client):
    response = client.post("/v1/register", json=pair_json(synthetic_pair(SEED), **CHEAP))
    assert response.status_code == 200
    return response.json()["transform"]


@pytest.fixture
def still_serves(client, reference):
    """After the test's bad request, a valid request still gets the same answer as before."""
    yield
    response = client.post("/v1/register", json=pair_json(synthetic_pair(SEED), **CHEAP))
    assert response.status_code == 200, response.text
    assert response.json()["transform"] == reference


def valid(**changes) -> dict:
    return {**pair_json(synthetic_pair(SEED)), **changes}


def with_row(row, index: int = 5) -> dict:
    body = valid()
    body["source"][index] = row
    return body


def raw_json(obj) -> bytes:
    return json.dumps(obj).encode()  # allows NaN / Infinity literals, as many clients send them


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=True)
    return buf.getvalue()


JSON_CASES = {
    "iterations_zero": (valid(iterations=0), 422, ["iterations", "greater than or equal to 1"]),
    "iterations_nine": (valid(iterations=9), 422, ["iterations", "less than or equal to 8"]),
    "iterations_text": (valid(iterations="many"), 422, ["iterations", "integer"]),
    "iterations_fraction": (valid(iterations=2.5), 422, ["iterations", "integer"]),
    "iterations_digits_as_text": (valid(iterations="4"), 422, ["iterations", "integer"]),
    "iterations_true": (valid(iterations=True), 422, ["iterations", "integer"]),
    "whole_float_out_of_range": (valid(refine_points=1e300), 422, ["refine_points", "less than or equal to 8192"]),
    "keypoints_too_few": (valid(keypoints=8), 422, ["keypoints"]),
    "keypoints_too_many": (valid(keypoints=1024), 422, ["keypoints"]),
    "refine_unknown": (valid(refine="magic"), 422, ["refine"]),
    "unknown_field": (valid(iteration=4), 422, ["iteration", "extra"]),
    "nan_coordinate": (with_row([0.1, float("nan"), 0.2]), 422, ["source[5][1]", "finite"]),
    "infinite_coordinate": (with_row([0.1, float("inf"), 0.2]), 422, ["source[5][1]", "finite"]),
    "two_column_row": (with_row([0.1, 0.2]), 422, ["source[5]", "at least 3"]),
    "four_column_row": (with_row([0.1, 0.2, 0.3, 0.4]), 422, ["source[5]", "at most 3"]),
    "text_coordinate": (with_row([0.1, "x", 0.3]), 422, ["source[5][1]"]),
    "flat_cloud": ({**valid(), "target": [0.1, 0.2, 0.3] * 40}, 422, ["target: a flat list of 120", "[40, 3]"]),
    # one row per axis inside a leading 1 (an array [1, 3, N] or [1, 4, N]): the advice was to reshape it, which
    # scrambles the points
    "one_row_per_axis_in_a_batch_of_one": ({**valid(), "target": [np.asarray(valid()["target"]).T.tolist()]}, 422,
                                           ["target: expected shape [N, 3], got [1, 3, ", "one row per axis",
                                            "transposed"]),
    "homogeneous_rows_in_a_batch_of_one": (
        {**valid(), "target": [np.vstack([np.asarray(valid()["target"]).T, np.ones(len(valid()["target"]))]).tolist()]},
        422, ["target: expected shape [N, 3], got [1, 4, ", "homogeneous", "cloud[:3].T"]),
    "too_few_points": ({**valid(), "source": [[0.0, 0.0, 0.1 * i] for i in range(10)]}, 422, ["source", "32"]),
    "missing_target": ({"source": valid()["source"]}, 422, ["target", "required"]),
    "not_an_object": ([1, 2, 3], 422, ["object"]),
    "transform_3x3": (valid(initial_transform=np.eye(3).tolist()), 422, ["initial_transform"]),
    "transform_not_rigid": (valid(initial_transform=(2 * np.eye(4)).tolist()), 422, ["initial_transform", "rigid"]),
    "unknown_model": (valid(model="no-such-model"), 404, ["unknown model"]),
    "path_as_model": (valid(model="../../etc/passwd"), 404, ["unknown model"]),
}


@pytest.mark.parametrize("case", list(JSON_CASES))
def test_rejects_bad_json_request(client, still_serves, case):
    body, status, words = JSON_CASES[case]
    response = client.post("/v1/register", content=raw_json(body), headers={"content-type": "application/json"})
    assert_error(response, status, *words)


@pytest.mark.parametrize(
    ("content", "content_type", "status", "words"),
    [
        (b'{"source": [[1, 2, 3]', "application/json", 400, ["malformed JSON"]),
        (b"", "application/json", 400, ["empty"]),
        (b"\xff\xfe\x00", "application/json", 400, ["malformed JSON"]),
        (b"source=1", "application/x-www-form-urlencoded", 415, ["content type"]),
        (b"hello", "text/plain", 415, ["content type", "application/json"]),
        (b"{}", "", 415, ["content type"]),
        (b"--x--", "multipart/form-data; boundary=x", 422, ["source", "missing"]),
    ],
)
def test_rejects_malformed_body_or_wrong_content_type(client, still_serves, content, content_type, status, words):
    headers = {"content-type": content_type} if content_type else {}
    assert_error(client.post("/v1/register", content=content, headers=headers), status, *words)


def test_whole_numbers_written_as_floats_are_taken(client, still_serves):
    """JSON Schema's ``integer`` (OpenAPI 3.1) takes 4.0, as serializers that write doubles send it (before: 422)."""
    as_ints = client.post("/v1/register", json=valid(iterations=2, keypoints=64, refine="icp", refine_points=1536))
    as_floats = client.post("/v1/register", json=valid(iterations=2.0, keypoints=64.0, refine="icp",
                                                          refine_points=1536.0))
    assert as_ints.status_code == as_floats.status_code == 200, as_floats.text
    assert as_floats.json()["transform"] == as_ints.json()["transform"] and as_floats.json()["iterations"] == 2


def test_batch_rejects_bad_pair_naming_it(client, still_serves):
    pairs = [valid(), valid(iterations=9)]
    assert_error(client.post("/v1/register/batch", json={"pairs": pairs}), 422, "pairs[1].iterations")
    assert_error(client.post("/v1/register/batch", json={"pairs": []}), 422, "pairs")
    assert_error(client.post("/v1/register/batch", content=b"x", headers={"content-type": "text/csv"}), 415)


def test_batch_checks_every_pair_before_running_any(client, still_serves):
    few = {**valid(), "target": [[0.0, 0.0, 0.1 * i] for i in range(40)]}  # collinear is allowed, unknown model not
    response = client.post("/v1/register/batch", json={"pairs": [few, valid(model="nope")]})
    assert_error(response, 404, "nope")


def multipart(source: bytes, target: bytes | None = None, **fields) -> dict:
    files = {"source": ("source.npy", source)}
    if target is not None:
        files["target"] = ("target.npy", target)
    return {"files": files, "data": fields}


PAIR = synthetic_pair(SEED)
MULTIPART_CASES = {
    "pickled_object_array": (multipart(npy(np.array([{"x": 1}] * 40, dtype=object)), npy(PAIR.target)), 422,
                             ["source", "object"]),
    "pickle_not_npy": (multipart(pickle.dumps(PAIR.source.tolist()), npy(PAIR.target)), 400, ["source", ".npy"]),
    "two_columns": (multipart(npy(PAIR.source[:, :2]), npy(PAIR.target)), 422, ["source", "[N, 3]"]),
    "complex_dtype": (multipart(npy(PAIR.source.astype(complex)), npy(PAIR.target)), 422, ["source", "complex"]),
    "nan_points": (multipart(npy(np.where(np.arange(len(PAIR.source))[:, None] == 7, np.nan, PAIR.source)),
                             npy(PAIR.target)), 422, ["source", "nan"]),
    "truncated": (multipart(npy(PAIR.source)[:200], npy(PAIR.target)), 400, ["source"]),
    "missing_target": (multipart(npy(PAIR.source)), 422, ["target", "missing"]),
    "bad_option": (multipart(npy(PAIR.source), npy(PAIR.target), iterations="9"), 422, ["iterations"]),
    "unknown_option": (multipart(npy(PAIR.source), npy(PAIR.target), speed="fast"), 422, ["speed"]),
    "bad_transform": (multipart(npy(PAIR.source), npy(PAIR.target), initial_transform="[[1"), 422,
                      ["initial_transform"]),
    "unknown_model": (multipart(npy(PAIR.source), npy(PAIR.target), model="../../etc/passwd"), 404,
                      ["unknown model"]),
}


@pytest.mark.parametrize("case", list(MULTIPART_CASES))
def test_rejects_bad_multipart_upload(client, still_serves, case):
    kwargs, status, words = MULTIPART_CASES[case]
    assert_error(client.post("/v1/register", **kwargs), status, *words)


def oip(source=None, target=None, **request) -> dict:
    def tensor(name, points, **overrides):
        points = np.asarray(points)
        return {"name": name, "shape": list(points.shape), "datatype": "FP32", "data": points.ravel().tolist(),
                **overrides}

    return {"inputs": [tensor("SOURCE", PAIR.source if source is None else source), tensor("TARGET", PAIR.target)],
            **request}


def _retyped(**overrides) -> dict:
    body = oip()
    body["inputs"][0].update(overrides)
    return body


OIP_CASES = {
    "fp64_datatype": (_retyped(datatype="FP64"), 422, ["SOURCE", "FP32"]),
    "wrong_shape": (_retyped(shape=[len(PAIR.source), 2]), 422, ["SOURCE", "shape"]),
    "shape_mismatch": (_retyped(shape=[10, 3]), 422, ["SOURCE", "values"]),
    "ragged": (_retyped(data=[[1.0, 2.0, 3.0], [1.0, 2.0]]), 422, ["SOURCE", "ragged"]),
    "text_data": (_retyped(data=["a"] * (3 * len(PAIR.source))), 422, ["SOURCE", "numbers"]),
    "nan_data": (raw_json(_retyped(data=[float("nan")] * (3 * len(PAIR.source)))), 422, ["SOURCE", "nan"]),
    "missing_target": ({"inputs": oip()["inputs"][:1]}, 422, ["TARGET", "missing"]),
    "unknown_input": ({"inputs": [*oip()["inputs"], {**oip()["inputs"][0], "name": "NORMALS"}]}, 422, ["NORMALS"]),
    "unknown_output": (oip(outputs=[{"name": "SCORES"}]), 422, ["SCORES"]),
    "bad_iterations": (oip(parameters={"iterations": 0}), 422, ["iterations"]),
    "bad_refine": (oip(parameters={"refine": "magic"}), 422, ["refine"]),
    "no_inputs": ({"inputs": []}, 422, ["inputs"]),
}


@pytest.mark.parametrize("case", list(OIP_CASES))
def test_rejects_bad_oip_infer_request(client, still_serves, case):
    body, status, words = OIP_CASES[case]
    content = body if isinstance(body, bytes) else raw_json(body)
    response = client.post(f"/v2/models/{MODEL}/infer", content=content, headers={"content-type": "application/json"})
    assert_error(response, status, *words)


@pytest.mark.parametrize(
    ("method", "path", "status"),
    [
        ("GET", "/v2/models/no-such-model", 404),
        ("GET", "/v2/models/no-such-model/ready", 404),
        ("POST", "/v2/models/no-such-model/infer", 404),
        ("GET", "/v2/models/..%2F..%2Fetc%2Fpasswd", 404),
        ("GET", "/v2/models/%2E%2E/ready", 404),
        ("GET", "/no/such/route", 404),
        ("GET", "/v1/register", 405),
        ("DELETE", "/v1/models", 405),
    ],
)
def test_unknown_models_and_routes_are_json_errors(client, still_serves, method, path, status):
    assert_error(client.request(method, path, json=oip() if method == "POST" else None), status)


def test_degenerate_clouds_get_an_answer_with_warnings(client, still_serves):
    same = [[0.5, 0.5, 0.5]] * 64
    line = [[0.01 * i, 0.02 * i, 0.03 * i] for i in range(64)]
    for cloud in (same, line):
        response = client.post("/v1/register", json={"source": cloud, "target": cloud})
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["quality"]["reliable"] is False and body["warnings"]


def test_a_multipart_body_with_an_epilogue_after_its_closing_boundary_registers(client, still_serves) -> None:
    """RFC 2046 allows text after the close delimiter; the check that a body was not cut short looks for the
    delimiter itself, not for the body's last bytes."""
    parts = [b'Content-Disposition: form-data; name="source"; filename="s.npy"\r\n\r\n' + npy(PAIR.source),
             b'Content-Disposition: form-data; name="target"; filename="t.npy"\r\n\r\n' + npy(PAIR.target),
             b'Content-Disposition: form-data; name="iterations"\r\n\r\n1']
    content = b"".join(b"--B\r\n" + part + b"\r\n" for part in parts) + b"--B--\r\n" + b"\r\n" * 1000
    response = client.post("/v1/register", content=content, headers={"content-type": "multipart/form-data; boundary=B"})
    assert response.status_code == 200, response.text


def multipart(source_headers: bytes, content_type: str = "multipart/form-data; boundary=B", extra: bytes = b"") -> dict:
    """A ``/v1/register`` upload whose source part has the ``Content-Disposition`` and headers ``source_headers``,
    and ``extra`` (a whole part: headers, blank line, value) after the target's part."""
    parts = [source_headers + b"\r\n\r\n" + npy(PAIR.source),
             b'Content-Disposition: form-data; name="target"; filename="t.npy"\r\n\r\n' + npy(PAIR.target)]
    parts += [extra] if extra else []
    content = b"".join(b"--B\r\n" + part + b"\r\n" for part in parts) + b"--B--\r\n"
    return {"content": content, "headers": {"content-type": content_type}}


def test_multipart_uploads_the_form_parser_would_misread_are_4xx_naming_the_problem(client, still_serves) -> None:
    """A file named only by RFC 5987's filename* was taken for a text field, a base64 part's text for the file's bytes
    ("the cloud is empty"), a body declared as UTF-16 had its part names decoded as UTF-16 (a field "潳牵散"), and a
    UTF-16 field part got a bare "invalid value"."""
    disposition = b'Content-Disposition: form-data; name="source"; filename="s.npy"'
    cases = [
        (multipart(b"Content-Disposition: form-data; name=\"source\"; filename*=UTF-8''%E6%97%A5.npy"), 422,
         ("source", "filename=", "RFC 7578")),
        (multipart(disposition + b"\r\nContent-Transfer-Encoding: base64"), 415,
         ("source", "Content-Transfer-Encoding", "base64")),
        (multipart(disposition, "multipart/form-data; boundary=B; charset=utf-16"), 415,
         ("charset", "utf-16", "UTF-8")),
        (multipart(disposition, extra=b'Content-Disposition: form-data; name="iterations"\r\n'
                                      b"Content-Type: text/plain; charset=utf-16\r\n\r\n" + "4".encode("utf-16")),
         400, ("iterations", "NUL", "UTF-8")),
    ]
    for request, status, words in cases:
        assert_error(client.post("/v1/register", **request), status, *words)
    fine = client.post("/v1/register", **multipart(disposition + b"\r\nContent-Transfer-Encoding: binary",
                                                   "multipart/form-data; boundary=B; charset=UTF-8"))
    assert fine.status_code == 200, fine.text
