"""Reliability battery: every bad input gets a clear JSON 4xx, the server stays healthy, nothing is lost.

Each case in ``BAD_INPUTS`` is sent to a real uvicorn server (``/v1/register`` JSON and multipart,
``/v1/register/batch`` and OIP v2 ``infer``). For every case: the status and a keyword of the
``{"error": ...}`` message; no traceback, internal path or source file name in the body;
``/v2/health/ready`` still 200; and the next valid request gets exactly the reference transform.

Degenerate but valid geometry (``GEOMETRY``) is answered 200 with a pose, and honestly:
``quality.reliable`` is false with a warning where the pose cannot be determined (identical,
collinear), a warning only where it may be ambiguous (coplanar), and the same pose as the
reference, moved or scaled, for far-apart or tiny clouds. The table in docs/RELIABILITY.md lists
the cases and their statuses.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import re
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from api_server import LIMITED, MODEL, REPO, assert_error, limited_server, main_server, model_root, modelnet_pair

SEED = 3  # the pair every case starts from (partial views of a ModelNet40 shape, 700 points each)
CHEAP = {"iterations": 1, "keypoints": 16}  # a quick valid request for the after-check
AUTH = {"Authorization": f"Bearer {LIMITED['api_key']}"}
SMALL = 300  # points per cloud on the limited server (max_points 400)
INFER = f"/v2/models/{MODEL}/infer"
MARKER = Path(tempfile.gettempdir()) / f"mfgnet-unpickled-{os.getpid()}"  # created only if a pickle ran
LEAKS = ("Traceback", "/work/", str(REPO), '.py"', 'File "', "site-packages")


# -- servers and the reference answer ---------------------------------------------------------------
@dataclass
class Target:
    """A server, its client headers, and the transform it answers for the reference request."""

    client: httpx.Client
    reference_body: dict
    reference: list = field(default_factory=list)

    def reference_call(self) -> httpx.Response:
        return self.client.post("/v1/register", json=self.reference_body)


def _pair(n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    pair = modelnet_pair(SEED)
    return pair.source[:n].astype(np.float64), pair.target[:n].astype(np.float64)


@pytest.fixture(scope="session")
def targets():
    """``main``: default limits; ``limited``: max_points 400, max_body_bytes 200 kB, API key."""
    main, limited = main_server(), limited_server()
    src, tgt = _pair()
    small_src, small_tgt = _pair(SMALL)
    out = {
        "main": Target(main.client(), {"source": src.tolist(), "target": tgt.tolist(), **CHEAP}),
        "limited": Target(limited.client(headers=AUTH),
                          {"source": small_src.tolist(), "target": small_tgt.tolist(), **CHEAP}),
    }
    for target in out.values():
        response = target.reference_call()
        assert response.status_code == 200, response.text
        target.reference = response.json()["transform"]
    yield out
    for target in out.values():
        target.client.close()


# -- request builders -------------------------------------------------------------------------------
def raw_json(obj: Any) -> bytes:
    return json.dumps(obj).encode()  # writes NaN / Infinity literals, as many clients do


def jpost(body: Any, path: str = "/v1/register") -> dict:
    content = body if isinstance(body, bytes) else raw_json(body)
    return {"method": "POST", "url": path, "content": content, "headers": {"content-type": "application/json"}}


def body(**changes) -> dict:
    src, tgt = _pair()
    return {"source": src.tolist(), "target": tgt.tolist(), **changes}


def small_body(**changes) -> dict:
    """A valid body for the limited server (``SMALL`` points per cloud)."""
    src, tgt = _pair(SMALL)
    return {"source": src.tolist(), "target": tgt.tolist(), **changes}


def row(value, index: int = 5) -> dict:
    """The valid body with ``source[index]`` replaced by ``value``."""
    out = body()
    out["source"][index] = value
    return out


def columns(rows: list) -> dict:
    """``rows`` of x, y, z as an object of three arrays (a struct of arrays)."""
    return dict(zip("xyz", np.asarray(rows).T.tolist(), strict=True))


def coord(value) -> dict:
    """The valid body with ``source[5][1]`` replaced by ``value``."""
    return row([0.1, value, 0.2])


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=True)
    return buf.getvalue()


def npy_header(descr: str, shape: str, version: bytes = b"\x01\x00") -> bytes:
    """A ``.npy`` file with a hand-written header (and no data)."""
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}".encode()
    header += b" " * (63 - len(header)) + b"\n"
    return b"\x93NUMPY" + version + len(header).to_bytes(2, "little") + header


def form(source: bytes | None = None, target: bytes | None = None, **fields) -> dict:
    src, tgt = _pair()
    files = {"source": ("source.npy", npy(src) if source is None else source)}
    if target != b"":
        files["target"] = ("target.npy", npy(tgt) if target is None else target)
    return {"method": "POST", "url": "/v1/register", "files": files, "data": fields}


def multipart_without_its_closing_boundary(ending: bytes = b"") -> dict:
    """Both clouds and an option, the body ending before ``\\r\\n--B--`` (or with ``ending``): the option part was
    dropped silently."""
    src, tgt = _pair()
    parts = [b'Content-Disposition: form-data; name="source"; filename="s.npy"\r\n\r\n' + npy(src),
             b'Content-Disposition: form-data; name="target"; filename="t.npy"\r\n\r\n' + npy(tgt),
             b'Content-Disposition: form-data; name="refine"\r\n\r\nnone']
    content = b"".join(b"--B\r\n" + part + (b"\r\n" if i < 2 or not ending else b"") for i, part in enumerate(parts))
    return {"method": "POST", "url": "/v1/register", "content": content + ending,
            "headers": {"content-type": "multipart/form-data; boundary=B"}}


class Unpickler:
    """A pickle that, if the server ever unpickled it, would create ``MARKER``."""

    def __reduce__(self):
        return open, (str(MARKER), "w")


def oip(source: Any = None, target: Any = None, model: str = MODEL, raw: bool = False, **request) -> dict:
    """An OIP v2 infer request; ``source``/``target`` are arrays or full tensor dicts."""
    src, tgt = _pair()

    def tensor(name: str, value: Any) -> dict:
        if isinstance(value, dict):
            return {"name": name, "datatype": "FP32", **value}
        points = np.asarray(value)
        return {"name": name, "shape": list(points.shape), "datatype": "FP32", "data": points.ravel().tolist()}

    obj = {"inputs": [tensor("SOURCE", src if source is None else source),
                      tensor("TARGET", tgt if target is None else target)], **request}
    return jpost(obj if not raw else raw_json(obj), f"/v2/models/{model}/infer")


def data_of(values: list, n: int = 700) -> dict:
    """A SOURCE tensor dict ``[n, 3]`` whose data are ``values``."""
    return {"shape": [n, 3], "data": values}


def batch(*pairs: dict) -> dict:
    return jpost({"pairs": list(pairs)}, "/v1/register/batch")


def line(n: int = 64) -> list:
    return [[0.01 * i, 0.02 * i, 0.03 * i] for i in range(n)]


def raw(content: bytes, content_type: str | None, path: str = "/v1/register") -> dict:
    headers = {"content-type": content_type} if content_type else {}
    return {"method": "POST", "url": path, "content": content, "headers": headers}


# -- the battery ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    request: Callable[[], dict]  # kwargs of httpx.Client.request, built lazily (the data may be absent)
    status: int
    words: tuple[str, ...]
    server: str = "main"


def case(request: Callable[[], dict], status: int, *words: str, server: str = "main") -> Case:
    return Case(request, status, words, server)


BIG = LIMITED["max_points"] + 1
BAD_INPUTS: dict[str, Case] = {
    # non-finite and out-of-range numbers
    "nan_coordinate": case(lambda: jpost(coord(float("nan"))), 422, "source[5][1]", "finite"),
    "inf_coordinate": case(lambda: jpost(coord(float("inf"))), 422, "source[5][1]", "finite"),
    "minus_inf_coordinate": case(lambda: jpost(coord(float("-inf"))), 422, "source[5][1]", "finite"),
    "nan_in_target": case(lambda: jpost({**body(), "target": [[float("nan")] * 3] * 40}), 422, "target", "finite"),
    "float32_overflow_1e39": case(lambda: jpost(coord(1e39)), 422, "source", "float32"),
    "literal_1e400_is_infinite": case(lambda: jpost(raw_json(coord(0.123456789)).replace(b"0.123456789", b"1e400")),
                                      422, "source[5][1]", "finite"),
    "integer_with_5000_digits": case(lambda: jpost(b'{"source": [[' + b"1" * 5000 + b", 0, 0]]}"), 400,
                                     "malformed JSON", "digits"),
    # shapes
    "empty_source": case(lambda: jpost({**body(), "source": []}), 422, "source", "at least 32"),
    "empty_both": case(lambda: jpost({"source": [], "target": []}), 422, "source", "target", "32"),
    "31_points": case(lambda: jpost({**body(), "source": body()["source"][:31]}), 422, "source", "32"),
    "row_of_2": case(lambda: jpost(row([0.1, 0.2])), 422, "source[5]", "at least 3"),
    "row_of_4": case(lambda: jpost(row([0.1, 0.2, 0.3, 0.4])), 422, "source[5]", "at most 3"),
    "empty_row": case(lambda: jpost(row([])), 422, "source[5]", "at least 3"),
    "ragged_rows": case(lambda: jpost({**body(), "target": [[0.1, 0.2], [0.1, 0.2, 0.3, 0.4]] * 20}), 422,
                        "target[0]", "target[1]"),
    "flat_cloud": case(lambda: jpost({**body(), "target": [0.1, 0.2, 0.3] * 40}), 422, "target: a flat list of 120",
                       "reshape it to [40, 3]"),
    "two_columns": case(lambda: jpost({**body(), "source": [r[:2] for r in body()["source"]]}), 422,
                        "source: expected shape [N, 3]", ", 2]"),
    "six_columns": case(lambda: jpost({**body(), "source": [r + r for r in body()["source"]]}), 422,
                        "source: expected shape [N, 3]", ", 6]", "x, y, z only"),
    "one_row_per_axis": case(lambda: jpost({**body(), "target": np.asarray(body()["target"]).T.tolist()}), 422,
                             "target: expected shape [N, 3], got [3, ", "one row per axis"),
    "columns_as_an_object": case(lambda: jpost({**body(), "source": columns(body()["source"])}), 422,
                                 "source: a JSON object", "send them as rows"),
    "cloud_is_a_string": case(lambda: jpost({**body(), "source": "0 0 0"}), 422, "source", "list"),
    "cloud_is_an_object": case(lambda: jpost({**body(), "source": {"x": [1.0]}}), 422, "source", "list"),
    # wrong types where numbers belong
    "string_coordinate": case(lambda: jpost(coord("x")), 422, "source[5][1]", "number"),
    "numeric_string_coordinate": case(lambda: jpost(coord("1.5")), 422, "source[5][1]", "number"),
    "boolean_coordinate": case(lambda: jpost(coord(True)), 422, "source[5][1]", "number"),
    "null_coordinate": case(lambda: jpost(coord(None)), 422, "source[5][1]", "number"),
    "object_coordinate": case(lambda: jpost(coord({"value": 1.0})), 422, "source[5][1]", "number"),
    "list_coordinate": case(lambda: jpost(coord([1.0])), 422, "source[5][1]", "number"),
    "null_row": case(lambda: jpost(row(None)), 422, "source[5]", "list"),
    # options
    "iterations_0": case(lambda: jpost(body(iterations=0)), 422, "iterations", "greater than or equal to 1"),
    "iterations_9": case(lambda: jpost(body(iterations=9)), 422, "iterations", "less than or equal to 8"),
    "iterations_true": case(lambda: jpost(body(iterations=True)), 422, "iterations", "integer"),
    "iterations_2.5": case(lambda: jpost(body(iterations=2.5)), 422, "iterations", "integer"),
    "iterations_string": case(lambda: jpost(body(iterations="4")), 422, "iterations", "integer"),
    "keypoints_8": case(lambda: jpost(body(keypoints=8)), 422, "keypoints", "16"),
    "keypoints_1024": case(lambda: jpost(body(keypoints=1024)), 422, "keypoints", "512"),
    "refine_unknown": case(lambda: jpost(body(refine="magic")), 422, "refine", "none", "icp"),
    "transform_not_rigid": case(lambda: jpost(body(initial_transform=(2 * np.eye(4)).tolist())), 422,
                                "initial_transform", "rigid"),
    "transform_with_nan": case(lambda: jpost(body(initial_transform=[[float("nan")] * 4] * 4)), 422,
                               "initial_transform", "finite"),
    "transform_moves_past_float32": case(
        lambda: jpost(body(initial_transform=[[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])), 422,
        "initial_transform", "float32"),
    # models: names are looked up, never opened
    "unknown_model": case(lambda: jpost(body(model="no-such-model")), 404, "unknown model", "no-such-model"),
    "model_is_a_relative_path": case(lambda: jpost(body(model="../../etc/passwd")), 404, "unknown model"),
    "model_is_an_absolute_path": case(lambda: jpost(body(model="/etc/passwd")), 404, "unknown model"),
    "model_is_a_real_model_folder": case(lambda: jpost(body(model=str(model_root() / MODEL))), 404,
                                         "unknown model"),
    "model_name_too_long": case(lambda: jpost(body(model="m" * 200)), 422, "model", "128"),
    "model_name_empty": case(lambda: jpost(body(model="")), 422, "model", "at least 1 character"),
    "multipart_model_name_empty": case(lambda: form(model=""), 422, "model", "at least 1 character"),
    # fields
    "missing_source": case(lambda: jpost({"target": body()["target"]}), 422, "source", "required"),
    "missing_target": case(lambda: jpost({"source": body()["source"]}), 422, "target", "required"),
    "empty_object": case(lambda: jpost({}), 422, "source", "target", "required"),
    "unknown_field_is_refused": case(lambda: jpost(body(iteration=4)), 422, "iteration", "extra"),
    "body_is_an_array": case(lambda: jpost([1, 2, 3]), 422, "object"),
    "body_is_null": case(lambda: jpost(b"null"), 422, "object"),
    # malformed bodies and content types
    "truncated_json": case(lambda: raw(b'{"source": [[1, 2, 3]', "application/json"), 400, "malformed JSON"),
    "trailing_garbage": case(lambda: raw(b"{} x", "application/json"), 400, "malformed JSON"),
    "empty_body": case(lambda: raw(b"", "application/json"), 400, "empty"),
    "not_utf8": case(lambda: raw(b"\xff\xfe\x00", "application/json"), 400, "malformed JSON", "UTF-8"),
    "nested_100k_deep": case(lambda: raw(b"[" * 100_000 + b"]" * 100_000, "application/json"), 400,
                             "malformed JSON", "nested"),
    "content_type_text_plain": case(lambda: raw(b"{}", "text/plain"), 415, "content type", "application/json"),
    "content_type_missing": case(lambda: raw(b"{}", None), 415, "content type"),
    "content_type_urlencoded": case(lambda: raw(b"source=1", "application/x-www-form-urlencoded"), 415,
                                    "content type"),
    "content_type_xml": case(lambda: raw(b"<source/>", "application/xml"), 415, "content type"),
    # multipart .npy uploads
    "npy_random_bytes": case(lambda: form(source=os.urandom(256)), 400, "source", ".npy"),
    "npy_truncated": case(lambda: form(source=npy(_pair()[0])[:300]), 400, "source", ".npy"),
    "npy_header_is_code": case(lambda: form(source=b"\x93NUMPY\x01\x00\x10\x00__import__('os')\n"), 400,
                               "source", ".npy"),
    "npy_empty_shape_beyond_any_array": case(lambda: form(source=npy_header("<f8", "(0, 9223372036854775808)")), 400,
                                             "source", ".npy", "beyond"),
    "multipart_without_its_closing_boundary": case(multipart_without_its_closing_boundary, 400, "closing boundary",
                                                   "cut short"),
    "multipart_closing_boundary_without_its_crlf": case(lambda: multipart_without_its_closing_boundary(b"--B--\r\n"),
                                                        400, "closing boundary", "cut short"),
    "npy_version_3": case(lambda: form(source=npy_header("<f8", "(40, 3)", b"\x03\x00")), 400, "source",
                          "version"),
    "npy_pickled_object_array": case(lambda: form(source=npy(np.array([Unpickler()] * 40, dtype=object))), 422,
                                     "source", "object", "pickle"),
    "raw_pickle_not_npy": case(lambda: form(source=pickle.dumps([Unpickler()] * 40)), 400, "source", ".npy"),
    "npy_complex_dtype": case(lambda: form(source=npy(_pair()[0].astype(complex))), 422, "source", "complex"),
    "npy_2_columns": case(lambda: form(source=npy(_pair()[0][:, :2])), 422, "source", "[N, 3]"),
    "npy_nan": case(lambda: form(source=npy(np.full((40, 3), np.nan))), 422, "source", "nan"),
    "npy_float32_overflow": case(lambda: form(source=npy(_pair()[0] * 1e39)), 422, "source", "float32"),
    "npy_float64_1e-165": case(lambda: form(source=npy(_pair()[0].astype(np.float64) * 1e-165)), 422, "source",
                               "too small"),
    "npy_31_points": case(lambda: form(source=npy(_pair()[0][:31])), 422, "source", "32"),
    "multipart_missing_target": case(lambda: form(target=b""), 422, "target", "missing"),
    "multipart_source_as_text": case(lambda: {"method": "POST", "url": "/v1/register", "data": {"source": "1,2,3"},
                                              "files": {"target": ("t.npy", npy(_pair()[1]))}}, 422, "source",
                                     "file"),
    "multipart_unknown_field": case(lambda: form(speed="fast"), 422, "speed", "extra"),
    "multipart_iterations_9": case(lambda: form(iterations="9"), 422, "iterations"),
    "multipart_transform_5000_digits": case(lambda: form(initial_transform="1" * 5000), 422, "initial_transform"),
    "multipart_model_is_a_path": case(lambda: form(model="../../etc/passwd"), 404, "unknown model"),
    "multipart_without_boundary": case(lambda: raw(b"--x--", "multipart/form-data"), 400, "boundary"),
    # OIP v2 infer
    "oip_nan": case(lambda: oip(data_of([float("nan")] * 2100), raw=True), 422, "SOURCE", "nan"),
    "oip_inf": case(lambda: oip(data_of([float("inf")] * 2100), raw=True), 422, "SOURCE", "infinite"),
    "oip_float32_overflow": case(lambda: oip(_pair()[0] * 1e39), 422, "SOURCE", "beyond the FP32 range"),
    "oip_empty": case(lambda: oip({"shape": [0, 3], "data": []}), 422, "source", "32"),
    "oip_31_points": case(lambda: oip(_pair()[0][:31]), 422, "source", "32"),
    "oip_shape_2_columns": case(lambda: oip(_pair()[0][:, :2]), 422, "SOURCE", "shape"),
    "oip_shape_4_columns": case(lambda: oip(np.hstack([_pair()[0], _pair()[0][:, :1]])), 422, "SOURCE", "shape"),
    "oip_ragged": case(lambda: oip(data_of([[1.0, 2.0, 3.0], [1.0, 2.0]], 2)), 422, "SOURCE", "ragged"),
    "oip_shape_mismatch": case(lambda: oip(data_of([0.5] * 30)), 422, "SOURCE", "values"),
    "oip_strings": case(lambda: oip(data_of(["1.5"] * 2100)), 422, "SOURCE", "numbers", "str"),
    "oip_booleans": case(lambda: oip(data_of([True] * 2100)), 422, "SOURCE", "numbers", "bool"),
    "oip_one_boolean": case(lambda: oip(data_of([True, *([0.5] * 2099)])), 422, "SOURCE", "numbers", "bool"),
    "oip_nulls": case(lambda: oip(data_of([None] * 2100)), 422, "SOURCE", "numbers"),
    "oip_objects": case(lambda: oip(data_of([{"x": 1}] * 2100)), 422, "SOURCE", "numbers", "dict"),
    "oip_fp64": case(lambda: oip({"shape": [700, 3], "datatype": "FP64", "data": [0.5] * 2100}), 422, "SOURCE",
                     "FP32"),
    "oip_transform_beyond_float64": case(lambda: jpost({"inputs": [*oip_inputs(), {
        "name": "INITIAL_TRANSFORM", "shape": [4, 4], "datatype": "FP32", "data": [10**400] + [0] * 15}]}, INFER), 422,
                                         "INITIAL_TRANSFORM", "float64"),
    "oip_missing_target": case(lambda: jpost({"inputs": oip_inputs()[:1]}, INFER), 422, "TARGET", "missing"),
    "oip_iterations_0": case(lambda: oip(parameters={"iterations": 0}), 422, "iterations"),
    "oip_iterations_true": case(lambda: oip(parameters={"iterations": True}), 422, "iterations", "integer"),
    "oip_keypoints_1024": case(lambda: oip(parameters={"keypoints": 1024}), 422, "keypoints"),
    "oip_unknown_model": case(lambda: oip(model="no-such-model"), 404, "unknown model"),
    "oip_model_is_dot_dot": case(lambda: oip(model="%2E%2E"), 404, "unknown model"),
    "oip_model_is_encoded_path": case(lambda: oip(model="..%2F..%2Fetc%2Fpasswd"), 404, "not found"),
    "oip_malformed_json": case(lambda: raw(b'{"inputs": [', "application/json", INFER), 400, "malformed JSON"),
    "oip_content_type_text": case(lambda: raw(b"{}", "text/plain", INFER), 415, "content type"),
    # batch
    "batch_nan_in_second_pair": case(lambda: batch(body(), coord(float("nan"))), 422, "pairs[1]", "finite"),
    "batch_empty": case(lambda: batch(), 422, "pairs"),
    "batch_content_type_csv": case(lambda: raw(b"x", "text/csv", "/v1/register/batch"), 415, "content type"),
    # limits (the limited server: max_points 400, max_body_bytes 200 kB)
    "json_over_max_points": case(lambda: jpost({"source": _pair(SMALL)[0].tolist(), "target": _pair()[1].tolist()}),
                                 413, "target", "700", "MFGNET_MAX_POINTS", server="limited"),
    "npy_over_max_points": case(lambda: form(npy(_pair(SMALL)[0]), npy(np.zeros((BIG, 3)))), 413, "target",
                                "MFGNET_MAX_FILE_POINTS", server="limited"),
    "npy_header_claims_10M_points": case(lambda: form(source=npy_header("<f8", "(10000000, 3)")), 413, "source",
                                         "MFGNET_MAX_FILE_POINTS", server="limited"),
    "oip_over_max_points": case(lambda: oip(_pair()[0][:BIG], _pair()[1][:SMALL]), 413, "SOURCE", "MFGNET_MAX_POINTS",
                                server="limited"),
    "json_arrays_and_objects_beyond_the_clouds": case(lambda: jpost(small_body(x=[{}] * 6000)), 413,
                                                      "arrays and objects", "MFGNET_MAX_POINTS", server="limited"),
    "batch_arrays_and_objects_beyond_the_clouds": case(lambda: batch(small_body(x=[[]] * 20_000)), 413,
                                                       "arrays and objects", "MFGNET_MAX_POINTS", server="limited"),
    "batch_points_beyond_one_pairs": case(lambda: batch(small_body(), small_body()), 413, "points in all",
                                          "2 x MFGNET_MAX_POINTS", server="limited"),
    "json_numbers_beyond_the_clouds": case(lambda: jpost(small_body(x=[1.5] * 8000)), 413, "values",
                                           "MFGNET_MAX_POINTS", server="limited"),
    "oip_numbers_beyond_the_clouds": case(lambda: oip(_pair(SMALL)[0], _pair(SMALL)[1], x=[1.5] * 8000), 413,
                                          "values", "MFGNET_MAX_POINTS", server="limited"),
    "oip_arrays_and_objects_beyond_the_clouds": case(lambda: oip({"shape": [SMALL, 3], "data": [[]] * 6000}), 413,
                                                     "arrays and objects", "MFGNET_MAX_POINTS", server="limited"),
    "json_key_text_beyond_the_options": case(lambda: jpost(small_body(**{f"k{i:04d}{'x' * 95}": 1 for i in range(999)})
                                                           ), 413, "bytes of strings", server="limited"),
    "json_strings_beyond_the_options": case(lambda: jpost(small_body(x=["a"] * 5000)), 413, "5003 strings", "4096",
                                            server="limited"),
    "oip_text_beyond_the_options": case(lambda: oip(_pair(SMALL)[0], _pair(SMALL)[1], id="a" * 70_000), 413,
                                        "bytes of strings", server="limited"),
    "initial_transform_as_a_file": case(lambda: {**form(), "files": {**form()["files"], "initial_transform": (
        "prior.json", b"[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]")}}, 400, "more file uploads than source and target",
        "the options) is a text field, not a file"),
    "source_file_given_twice": case(lambda: {**form(), "files": [("source", form()["files"]["source"])] * 2 + [
        ("target", form()["files"]["target"])]}, 400, "more file uploads than source and target (one file each)",
        "a file field given twice"),
    "cloud_sent_as_a_text_field": case(lambda: {**form(), "files": {"target": form()["files"]["target"]},
                                            "data": {"source": "0.125 0.25 0.5\n" * 6000}}, 400,
                                       "a text field is over 64 KiB", "source and target as file uploads",
                                       "-F source=@FILE"),
    "option_sent_to_the_aligned_route": case(lambda: {"method": "POST", "url": "/v1/register/aligned",
                                                  "files": {"source": form()["files"]["source"]},
                                                  "data": {"transform": json.dumps(np.eye(4).tolist()),
                                                           "refine": "none"}}, 422,
                                             "refine: Extra inputs are not permitted", "the field transform"),
    "cloud_rows_of_one_row": case(lambda: jpost({**body(), "source": [[r] for r in body()["source"]]}), 422,
                                  "source: expected shape [N, 3]", ", 1, 3]", "reshape it to [N, 3]"),
    "batch_npy_file_sent_as_json": case(lambda: raw(npy(_pair(SMALL)[0]), "application/json", "/v1/register/batch"),
                                        400, "malformed JSON", "NUMPY", '{"pairs": [...]}'),
    "npy_file_sent_as_json": case(lambda: raw(npy(_pair(SMALL)[0]), "application/json"), 400, "malformed JSON",
                                  "NUMPY", "begins no JSON value", "multipart/form-data"),
    "multipart_body_sent_as_json": case(lambda: raw(b"--x\r\nContent-Disposition: form-data; name=source; "
                                                    b"filename=s.npy\r\n\r\n" + npy(_pair(SMALL)[0]) + b"\r\n--x--\r\n",
                                                    "application/json"), 400, "malformed JSON", "begins with b'--x"),
    "json_coordinates_as_strings": case(lambda: jpost({"source": [[str(v) for v in p] for p in _pair(SMALL)[0]] * 5,
                                                       "target": _pair(SMALL)[1].tolist()}), 413, "strings",
                                        "coordinates are JSON numbers, not strings", server="limited"),
    "body_over_max_body_bytes": case(lambda: raw(b"[" * 250_000, "application/json"), 413, "MFGNET_MAX_BODY_BYTES",
                                     server="limited"),
}


def oip_inputs() -> list:
    return json.loads(oip()["content"])["inputs"]


def assert_no_leak(response: httpx.Response) -> None:
    for leak in LEAKS:
        assert leak not in response.text, (leak, response.text[:300])


def assert_still_serves(target: Target) -> None:
    ready = target.client.get("/v2/health/ready")
    assert ready.status_code == 200, ready.text
    after = target.reference_call()
    assert after.status_code == 200, after.text
    assert after.json()["transform"] == target.reference


@pytest.mark.parametrize("name", list(BAD_INPUTS))
def test_bad_input_is_a_clear_4xx_and_the_server_carries_on(targets, name):
    bad = BAD_INPUTS[name]
    target = targets[bad.server]
    response = target.client.request(**bad.request())
    assert_error(response, bad.status, *bad.words)
    assert_no_leak(response)
    assert response.headers.get("x-request-id")
    assert not MARKER.exists(), "the server unpickled an upload"
    assert_still_serves(target)


def test_the_reliability_table_lists_every_case_as_it_is_run():
    rows = re.findall(r"^\| (\d+) \| `([^`]+)` \| [^|]+ \| (\w+) \| (\d{3}) \| (.+) \|$",
                      (REPO / "docs" / "RELIABILITY.md").read_text(), re.MULTILINE)
    listed = [(int(number), name, server, int(status), tuple(re.findall(r"`([^`]+)`", words)))
              for number, name, server, status, words in rows]
    run = [(number, name, c.server, c.status, c.words) for number, (name, c) in enumerate(BAD_INPUTS.items(), 1)]
    assert listed == run


def test_content_length_over_the_limit_is_refused_before_the_body_is_sent(targets):
    """A 1 GB Content-Length with no body at all: 413 at once, so nothing was read or parsed."""
    url = httpx.URL(limited_server().url)
    started = time.perf_counter()
    with socket.create_connection((url.host, url.port), timeout=5) as sock:
        sock.sendall(
            b"POST /v1/register HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n"
            b"Content-Length: 1000000000\r\nAuthorization: " + AUTH["Authorization"].encode() + b"\r\n\r\n"
        )
        reply = b""
        # headers and body may come apart
        while b"MFGNET_MAX_BODY_BYTES" not in reply and time.perf_counter() - started < 5:
            chunk = sock.recv(65536)
            if not chunk:
                break
            reply += chunk
        reply = reply.decode("latin-1")
    assert reply.startswith("HTTP/1.1 413"), reply[:200]
    assert "MFGNET_MAX_BODY_BYTES" in reply and time.perf_counter() - started < 2
    assert_still_serves(targets["limited"])


# -- degenerate but valid geometry ------------------------------------------------------------------
def rotation_error_deg(R_est, R_true) -> float:
    cos = (np.trace(np.asarray(R_est) @ np.asarray(R_true).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def assert_pose(transform) -> tuple[np.ndarray, np.ndarray]:
    T = np.asarray(transform, dtype=np.float64)
    assert T.shape == (4, 4) and np.isfinite(T).all()
    R, t = T[:3, :3], T[:3, 3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)
    return R, t


def plane() -> np.ndarray:
    points = _pair()[0].copy()
    points[:, 2] = 0.0
    return points


GEOMETRY: dict[str, tuple[Callable[[], tuple[Any, Any]], str | None, bool | None]] = {
    # name: (source, target), expected warning kind, expected reliable (None: the quality check decides)
    "identical": (lambda: ([[0.5, 0.5, 0.5]] * 64, [[0.5, 0.5, 0.5]] * 64), "identical", False),
    "identical_source_only": (lambda: ([[0.5, 0.5, 0.5]] * 64, _pair()[1]), "identical", False),
    "collinear": (lambda: (line(), [[x + 0.1, y, z] for x, y, z in line()]), "collinear", False),
    "coplanar": (lambda: (plane(), plane() + np.array([0.1, 0.0, 0.0])), "coplanar", None),
    "duplicated": (lambda: (np.repeat(_pair()[0], 2, axis=0), np.repeat(_pair()[1], 2, axis=0)), None, None),
    # 20 points of the shape and a stack of 300 at one of them: the stack must not pass for overlap
    "few_distinct": (lambda: (np.repeat(_pair()[0][:20], [301] + [1] * 19, axis=0),
                              np.repeat(_pair()[1][:20], [301] + [1] * 19, axis=0)), "few distinct points", False),
}


@pytest.mark.parametrize("name", list(GEOMETRY))
def test_degenerate_geometry_gets_a_pose_and_an_honest_quality(targets, name):
    make, kind, reliable = GEOMETRY[name]
    source, target = make()
    client = targets["main"].client
    response = client.post("/v1/register", json={"source": np.asarray(source).tolist(),
                                                  "target": np.asarray(target).tolist()})
    assert response.status_code == 200, response.text
    result = response.json()
    R, _ = assert_pose(result["transform"])
    warnings = " ".join(result["warnings"])
    if kind is not None:
        assert kind in warnings
    else:
        assert not any(word in warnings for word in ("identical", "collinear", "coplanar", "few distinct"))
    if reliable is not None:
        assert result["quality"]["reliable"] is reliable
    if name == "duplicated":  # the same shape, each point twice: still close to the truth
        assert rotation_error_deg(R, modelnet_pair(SEED).rotation) < 10
    assert_still_serves(targets["main"])


@pytest.mark.parametrize(
    ("name", "move"),
    [
        ("target_1e6_away", lambda s, t: (s, t + 1e6)),
        ("both_1e6_from_origin", lambda s, t: (s + 1e6, t + 1e6)),
        ("tiny_1e-6_scale", lambda s, t: (s * 1e-6, t * 1e-6)),
        ("huge_1e6_scale", lambda s, t: (s * 1e6, t * 1e6)),
    ],
)
def test_far_apart_or_rescaled_clouds_get_the_reference_pose_moved_or_scaled(targets, name, move):
    """Each cloud is centred and both are scaled together, so offsets and units do not change the rotation."""
    main = targets["main"]
    src, tgt = _pair()
    moved_src, moved_tgt = move(src, tgt)
    response = main.client.post("/v1/register", json={"source": moved_src.tolist(), "target": moved_tgt.tolist(),
                                                      **CHEAP})
    assert response.status_code == 200, response.text
    R, t = assert_pose(response.json()["transform"])
    R_ref, t_ref = assert_pose(main.reference)
    np.testing.assert_allclose(R, R_ref, atol=1e-5)
    # target' = R source' + t'  with  source' = a source + b, target' = a target + c  =>  t' = a t + c - R b
    a = float(np.linalg.norm(moved_src[1] - moved_src[0]) / np.linalg.norm(src[1] - src[0]))
    b, c = moved_src[0] - a * src[0], moved_tgt[0] - a * tgt[0]
    np.testing.assert_allclose(t, a * t_ref + c - R @ b, rtol=1e-6, atol=1e-6 * max(1.0, float(np.abs(c).max())))


def test_oip_degenerate_clouds_report_unreliable_with_warnings(targets):
    for cloud, kind in (([[0.5, 0.5, 0.5]] * 64, "identical"), (line(), "collinear")):
        response = targets["main"].client.post(INFER, content=oip(cloud, cloud)["content"],
                                               headers={"content-type": "application/json"})
        assert response.status_code == 200, response.text
        parameters = response.json()["parameters"]
        assert parameters["reliable"] is False and kind in parameters["warnings"]
    assert_still_serves(targets["main"])


def test_oip_ignores_unknown_fields_and_parameters(targets):
    """OIP lets clients add fields and parameters; /v1 refuses unknown fields (typos like ``iteration``)."""
    request = oip(parameters={**CHEAP, "priority": 3}, extension={"trace": True})
    obj = json.loads(request["content"])
    obj["inputs"][0]["parameters"] = {"colour_space": "sRGB"}  # binary_data_size is no longer unknown: OIP binary
    response = targets["main"].client.post(INFER, content=raw_json(obj), headers=request["headers"])
    assert response.status_code == 200, response.text
    transform = next(o for o in response.json()["outputs"] if o["name"] == "TRANSFORM")["data"]
    np.testing.assert_allclose(np.reshape(transform, (4, 4)), targets["main"].reference, atol=1e-5)
