"""Large JSON bodies: the ``/v1/register`` fast path (``service/api/json_clouds.py``) reads the clouds
piece by piece straight into numpy, and it changes nothing but the cost.

* The fast path answers exactly what the reference path (``json`` + ``RegisterRequest`` validation)
  answers, value for value and error for error, on plain and odd bodies, whatever the piece size.
* A 100k-point pair is decoded with bounded memory (tracemalloc: deterministic), and over HTTP the
  server's peak RSS grows by less than 3x the body for it (the reference path's Python tree and
  pydantic's copy took 6x). Memory is the guard, never time: no timing threshold here.

Figures and the commands that measured them: docs/BENCHMARKS.md, "HTTP overhead".
"""

from __future__ import annotations

import io
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from api_server import main_server
from shapes import bumpy_ellipsoid

from service.api import bodies, json_clouds
from service.api.errors import APIError

BIG = 100_000
MAX_POINTS = 200_000  # the server's default max_points


def big_pair() -> tuple[np.ndarray, np.ndarray]:
    source = bumpy_ellipsoid(BIG, 0, np.float32)
    return source, bumpy_ellipsoid(BIG, 1, np.float32) + np.float32(0.05)


def outcome(body: bytes, max_points: int):
    """What ``register_pair_from_json`` gives: the pair's options and arrays, or the error's status and text."""
    try:
        pair = bodies.register_pair_from_json(bytearray(body), max_points)
    except APIError as exc:
        return ("error", exc.status, exc.message, exc.extra)
    return ("ok", pair.options.model_dump(), pair.source.dtype, pair.source.tolist(), pair.target.tolist())


def reference_outcome(body: bytes, max_points: int, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(bodies, "split_register_body", lambda *args: None)
        return outcome(body, max_points)


ROWS = np.round(bumpy_ellipsoid(40, 3), 6).tolist()
TEXT = json.dumps(ROWS)


def cloud(coordinate: str | None = None, row: str | None = None) -> str:
    """``ROWS`` as JSON text with ``source[5][1]`` or row 5 replaced by a literal."""
    rows = [list(r) for r in ROWS]
    if coordinate is not None:
        rows[5][1] = "@@"
    if row is not None:
        rows[5] = "@@"
    return json.dumps(rows).replace('"@@"', coordinate if coordinate is not None else str(row))


def raw(template: str, source: str = TEXT, target: str = TEXT) -> bytes:
    return template.replace("SRC", source).replace("TGT", target).encode()


PAIR = '{"source": SRC, "target": TGT}'
PLAIN = {  # bodies the fast path must take
    "compact": json.dumps({"source": ROWS, "target": ROWS}, separators=(",", ":")).encode(),
    "spaced": raw(PAIR),
    "indented": json.dumps({"source": ROWS, "target": ROWS, "iterations": 2}, indent=2).encode(),
    "target_first_options_around": raw('{"refine": "icp", "target": TGT, "keypoints": 16, "source": SRC}'),
    "integers": raw(PAIR, json.dumps([[i, -i, 2 * i] for i in range(40)])),
    "huge_integer_coordinate": raw(PAIR, cloud(coordinate="123456789012345678901234")),
    "model_name": raw('{"source": SRC, "target": TGT, "model": "clean"}'),
}
ODD = {  # bodies with something unusual: the reference path decides, the answer must be the same
    "nan_literal": raw(PAIR, cloud(coordinate="NaN")),
    "infinity_literal": raw(PAIR, cloud(coordinate="1e400")),
    "boolean": raw(PAIR, cloud(coordinate="true")),
    "null": raw(PAIR, cloud(coordinate="null")),
    "string_number": raw(PAIR, cloud(coordinate='"1.5"')),
    "short_row": raw(PAIR, cloud(row="[0.1, 0.2]")),
    "long_row": raw(PAIR, cloud(row="[0.1, 0.2, 0.3, 0.4]")),
    "empty_row": raw(PAIR, cloud(row="[]")),
    "number_row": raw(PAIR, cloud(row="0.5")),
    "trailing_comma": raw(PAIR, TEXT[:-1] + ", ]"),
    "nested_deeper": raw('{"source": [SRC], "target": TGT}'),
    "too_few_points": raw(PAIR, json.dumps(ROWS[:31])),
    "duplicate_key_last_wins": raw('{"source": SRC, "target": TGT, "source": 5}'),
    "duplicate_key_cloud_last": raw('{"source": 5, "target": TGT, "source": SRC}'),
    "cloud_key_nested": raw('{"model": {"source": SRC}, "source": SRC, "target": TGT}'),
    "bracket_in_string": raw('{"source": SRC, "target": TGT, "model": "a]]b"}'),
    "escaped_string": raw('{"source": SRC, "target": TGT, "model": "cl\\u0065an"}'),
    "iterations_huge_integer": raw('{"source": SRC, "target": TGT, "iterations": 100000000000000000000000}'),
    "unknown_option": raw('{"source": SRC, "target": TGT, "iteration": 4}'),
    "bad_option": raw('{"source": SRC, "target": TGT, "refine": "magic"}'),
    "missing_target": raw('{"source": SRC}'),
    "top_level_array": raw('[{"source": SRC, "target": TGT}]'),
    "trailing_garbage": raw(PAIR + " x"),
    "truncated": raw(PAIR)[:-3],
    "not_utf8": raw('{"source": SRC, "target": TGT, "model": "M"}').replace(b'"M"', b'"\xff"'),
    "bom": b"\xef\xbb\xbf" + raw(PAIR),
}


@pytest.mark.parametrize("piece_bytes", [json_clouds.PIECE_BYTES, 64])
@pytest.mark.parametrize("name", list(PLAIN) + list(ODD))
def test_fast_path_answers_what_the_reference_path_answers(monkeypatch, name, piece_bytes):
    monkeypatch.setattr(json_clouds, "PIECE_BYTES", piece_bytes)  # 64: a piece per row or two
    body = {**PLAIN, **ODD}[name]
    for max_points in (MAX_POINTS, 35):  # 35: the 413 answer too
        assert outcome(body, max_points) == reference_outcome(body, max_points, monkeypatch), name
    if name in PLAIN:
        assert json_clouds.split_register_body(bytearray(body), MAX_POINTS) is not None, "fast path not taken"


def test_fast_path_decodes_100k_points_exactly_in_bounded_memory():
    source, target = big_pair()
    body = bytearray(json.dumps({"source": source.tolist(), "target": target.tolist(), "iterations": 2}).encode())
    tracemalloc.start()
    try:
        pair = bodies.register_pair_from_json(body, MAX_POINTS)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert pair.options.iterations == 2
    np.testing.assert_array_equal(pair.source, source.astype(np.float64))  # float32 -> JSON -> float64: exact
    np.testing.assert_array_equal(pair.target, target.astype(np.float64))
    arrays = pair.source.nbytes + pair.target.nbytes  # 4.6 MiB; measured peak 7.0 MiB, reference path 56 MiB
    assert peak < 3 * arrays, f"decoding took {peak / 2**20:.1f} MiB for {arrays / 2**20:.1f} MiB of arrays"


def _rss_mib(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no {field} for {pid}")


def _peak_growth_mib(pid: int, send) -> float:
    """How far the server's peak RSS rose above its RSS during ``send()`` (peak reset just before)."""
    before = _rss_mib(pid, "VmRSS")
    try:
        Path(f"/proc/{pid}/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    except OSError:
        pytest.skip("cannot reset the server's peak RSS (/proc/PID/clear_refs)")
    response = send()
    assert response.status_code == 200, response.text[:300]
    return _rss_mib(pid, "VmHWM") - before


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_100k_point_json_request_does_not_grow_the_server_by_its_json_tree():
    """The same 100k-point pair as .npy uploads first (so the pipeline's own memory for 100k inputs is
    allocated), then as JSON: the JSON request may add its body and arrays (measured: +11-16 MiB for
    a 12.3 MiB body), not a Python tree of 200k lists (the reference path: +74 MiB)."""
    server = main_server()
    pid = server.extra["proc"].pid
    source, target = big_pair()
    body = json.dumps({"source": source.tolist(), "target": target.tolist()}).encode()
    files = {"source": ("source.npy", npy(source)), "target": ("target.npy", npy(target))}
    with server.client() as client:
        _peak_growth_mib(pid, lambda: client.post("/v1/register", files=files))
        growth = _peak_growth_mib(
            pid, lambda: client.post("/v1/register", content=body, headers={"content-type": "application/json"})
        )
        answer = client.post("/v1/register", files=files).json()
    body_mib = len(body) / 2**20
    assert growth < 3 * body_mib, f"peak RSS rose {growth:.0f} MiB for a {body_mib:.1f} MiB JSON body"
    R = np.asarray(answer["rotation"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
